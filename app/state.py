"""The editor's UI-thread state: what the panels show and edit (no model, no GL objects)."""
from __future__ import annotations

from dataclasses import dataclass, field


@dataclass
class TrainingHistory:
    """Loss/PSNR against training step, for the live plot."""

    steps: list = field(default_factory=list)
    loss: list = field(default_factory=list)
    psnr: list = field(default_factory=list)

    def add(self, info: dict) -> None:
        if "step" not in info:
            return
        self.steps.append(float(info["step"]))
        self.loss.append(float(info.get("loss", float("nan"))))
        self.psnr.append(float(info.get("psnr", float("nan"))))
        if len(self.steps) > 5000:  # keep the plot cheap: drop every other old point
            for lst in (self.steps, self.loss, self.psnr):
                del lst[:2500:2]


@dataclass
class EditorState:
    """Everything the panels read and write; the editor turns changes into worker calls."""

    scene_path: str = ""
    workspace: str | None = None
    scene_info: dict = field(default_factory=dict)
    loading: bool = False
    view_mode: str = "rgb"
    tool: str = "navigate"  # or "select"
    threshold: float = 0.5
    auto_threshold: float | None = None  # the last patch's automatic threshold; the slider starts there
    select_rect: tuple | None = None  # (rect, mode) of the patch being selected
    has_selection: bool = False
    selection_busy: bool = False
    masks_done: int | None = None
    text_query: str = ""  # "Select by text" (needs a CLIP-aligned teacher and clip_path)
    prompt: str = ""
    bg_prompt: str = ""
    backend: str = "offline"
    sd_path: str = ""
    clip_path: str = ""
    lambda_unmask: float = 100.0
    steps: int = 200
    repaint_running: bool = False
    training: bool = True
    last_status: dict = field(default_factory=dict)
    history: TrainingHistory = field(default_factory=TrainingHistory)
    export_path: str = "render.png"
    video_path: str = "turntable.mp4"
    snap_index: int = 0
    messages: list = field(default_factory=list)  # (kind, text); kind in info / error
    error: str | None = None  # the last worker crash, shown until dismissed
    capabilities: dict = field(default_factory=dict)
    render_ms: float = 0.0
    render_scale: float = 0.0

    def say(self, text: str, kind: str = "info") -> None:
        self.messages.append((kind, text))
        del self.messages[:-6]

"""The editor's UI-thread state: what the panels show and edit (no model, no GL objects)."""
from __future__ import annotations

from dataclasses import dataclass, field

from core.train.history import TrainingHistory


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

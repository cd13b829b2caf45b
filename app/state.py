"""The editor's UI-thread state: what the panels show and edit (no model, no GL objects)."""
from __future__ import annotations

from dataclasses import dataclass, field

from repaint_nerf.core.repaint.config import RepaintConfig
from repaint_nerf.core.train.history import TrainingHistory


class ExportJob:
    """A running export: the worker thread reports progress into it and polls `cancel`; the UI draws it."""

    def __init__(self, kind: str, target: str):
        self.kind, self.target = kind, target
        self.fraction, self.text = 0.0, "starting"
        self.cancel = False

    def report(self, fraction: float, text: str) -> None:  # called on the worker thread
        self.fraction, self.text = float(fraction), str(text)

    def cancelled(self) -> bool:
        return self.cancel


@dataclass
class EditorState:
    """Everything the panels read and write; the editor turns changes into worker calls."""

    scene_path: str = ""
    workspace: str | None = None
    scene_info: dict = field(default_factory=dict)
    loading: bool = False
    repair_offer: str | None = None  # a workspace that failed to open as damaged: the Scene panel offers repair
    feature_model: str | None = None  # the Scene panel's feature teacher for Open; None: untouched (as before)
    view_mode: str = "rgb"
    tool: str = "navigate"  # or "select"
    threshold: float = 0.5
    auto_threshold: float | None = None  # the last patch's automatic threshold; the slider starts there
    select_rect: tuple | None = None  # (rect, mode) of the patch being selected
    has_selection: bool = False
    selection_busy: bool = False
    masks_done: int | None = None
    use_geometry: bool = True  # the field's geometry shapes the applied masks ('full'), else the voxel clean-up only
    text_query: str = ""  # "Select by text" (needs a CLIP-aligned teacher and clip_path)
    prompt: str = ""
    bg_prompt: str = ""
    backend: str = "offline"
    sd_path: str = ""
    clip_path: str = ""
    repaint_config: RepaintConfig = field(default_factory=RepaintConfig)  # the CLI's defaults; the panel edits it
    repaint_running: bool = False
    training: bool = True
    last_status: dict = field(default_factory=dict)
    history: TrainingHistory = field(default_factory=TrainingHistory)
    export_path: str = "render.png"
    video_path: str = "turntable.mp4"
    mesh_path: str = "export/mesh.glb"
    points_path: str = "export/points.ply"
    dataset_path: str = "export/dataset"
    camera_path_file: str = "export/camera_path.json"
    export_selection: bool = False  # mesh / points of the selection only
    mesh_resolution: int = 192
    path_keys: list = field(default_factory=list)  # recorded key views: (field-space c2w 4x4, vertical fov deg)
    path_frames: int = 96
    export_video_path: str = "export/video.mp4"
    video_height: int = 720  # pixels; the width follows the viewport's aspect
    export_job: ExportJob | None = None
    snap_index: int = 0
    photo_frame: bool = True  # the view keeps the training photos' aspect (a portrait capture shows portrait)
    messages: list = field(default_factory=list)  # (kind, text); kind in info / error
    error: str | None = None  # the last worker crash, shown until dismissed
    capabilities: dict = field(default_factory=dict)
    render_ms: float = 0.0
    render_scale: float = 0.0

    def say(self, text: str, kind: str = "info") -> None:
        self.messages.append((kind, text))
        del self.messages[:-6]

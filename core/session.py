"""The one way to assemble the program: open a trained workspace, or start (or resume) a reconstruction.

The editor's engine, every command and the benchmarks go through these two functions, so they agree on
which file holds the field (the current version, else the stage-1 checkpoint), on the scene as it was
trained (its path, downscale, kind and world -> field normalisation from the header), on the teachers (the
workspace's saved choices) and on the checks (a feature head where selection needs one).
"""
from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import torch

from repaint_nerf.core.device import get_device
from repaint_nerf.core.errors import UserError, WorkspaceError
from repaint_nerf.core.scene.loaders.common import DEFAULT_MAX_SIZE
from repaint_nerf.core.scene.loaders.detect import load_scene
from repaint_nerf.core.scene.scene import Scene
from repaint_nerf.core.train.checkpoint import Checkpoint, read_header
from repaint_nerf.core.train.header import CheckpointHeader, SceneFacts
from repaint_nerf.core.train.stage1 import CHECKPOINT_NAME, Stage1Trainer, TrainConfig, restore_field
from repaint_nerf.core.workspace.workspace import MARKER, Workspace

WORKSPACE_SUFFIX = ".repaint-nerf"
# settings key: the training images (names, in order) of the reconstruction; its appearance codes index them
TRAIN_FRAMES = "train_frames"


def is_workspace(path: str | Path) -> bool:
    """Whether `path` is a repaint-nerf workspace folder (it holds workspace.json)."""
    return (Path(path) / MARKER).is_file()


def default_workspace(data: str | Path) -> Path:
    """Where a dataset's or photo folder's workspace goes when none is given: beside it (never inside)."""
    data = Path(data).resolve()
    return data.parent / f"{data.name}{WORKSPACE_SUFFIX}"


def trained_path(ws: Workspace) -> Path:
    """The file of the workspace's field: its current version, else its stage-1 checkpoint."""
    version = ws.current_version
    path = ws.version_path(version) if version else ws.checkpoints_dir / CHECKPOINT_NAME
    if not path.exists():
        raise WorkspaceError("the workspace has no trained field yet", ws.root,
                             hint=f"run: repaint-nerf train SCENE --workspace {ws.root}")
    return path


def saved_header(ws: Workspace) -> CheckpointHeader | None:
    """The header of the workspace's stage-1 checkpoint, else of its current version (None when neither)."""
    ckpt = ws.checkpoints_dir / CHECKPOINT_NAME
    for path in (ckpt, ws.version_path(ws.current_version) if ws.current_version else None):
        if path is not None and path.exists():
            try:
                return read_header(path)
            except WorkspaceError:
                continue  # a damaged checkpoint: the version (or a fresh start) decides
    return None


def require_feature_head(header: CheckpointHeader, where: str | Path) -> None:
    """Raise a WorkspaceError when the field was trained without a feature head (nothing to select with)."""
    if header.feature_dim <= 0:
        raise WorkspaceError("this workspace's field was trained without a feature head, so it cannot select",
                             where, hint="train it again with teacher features (a feature head), then select")


def scene_root(ws: Workspace, facts: SceneFacts | None = None) -> Path:
    """The dataset folder a workspace belongs to (its settings, else the header's facts); a WorkspaceError
    when it is not recorded or has gone."""
    root = ws.settings.get("scene") or (facts.root if facts else None)
    if not root:
        raise WorkspaceError("this workspace does not say which scene it belongs to (settings.json)", ws.root,
                             hint="open the scene's dataset folder, or train: repaint-nerf train SCENE --workspace WS")
    if not Path(root).exists():
        raise WorkspaceError(f"the workspace's scene {root} is missing", ws.root,
                             hint="move the dataset back, or set 'scene' in settings.json")
    return Path(root)


def _load_with_settings(path: Path, ws: Workspace, kind: str | None, settings: dict | None = None) -> Scene:
    """Load `path` with the workspace's saved downscale, photo size cap and frame selection (so a reopened scene
    matches), or with `settings` where given (a run that has not saved its choices yet)."""
    settings = ws.settings if settings is None else settings
    return load_scene(path, float(settings.get("downscale", 1.0)), kind=kind, workspace=ws.root,
                      max_size=int(settings.get("max_size", DEFAULT_MAX_SIZE)),
                      sharpness_discard=settings.get("sharpness_discard"))


def workspace_scene(ws: Workspace, facts: SceneFacts | None = None) -> Scene:
    """The scene a workspace was trained on, loaded as it was then: its path, downscale and kind (from the
    header's facts when given, else the settings) and, when recorded, its world -> field normalisation."""
    settings = ws.settings
    kind = (facts.kind if facts else None) or settings.get("kind")
    scene = _load_with_settings(scene_root(ws, facts), ws, kind)
    norm = facts.normalization() if facts else None
    if norm is not None:
        scene.norm = norm  # the field lives in the space it was trained in
    return scene


@dataclass
class Trained:
    """A workspace's field ready to render: what `open_trained` returns."""

    workspace: Workspace
    scene: Scene
    field: torch.nn.Module
    grid: object  # core.render.occupancy.OccupancyGrid
    header: CheckpointHeader
    path: Path  # the checkpoint or version file it came from

    def render_options(self, **kw):
        """RenderOptions at the sample budget the field was trained with (as the editor renders it): a finer
        step costs more per view for the same picture (fox: 4x the budget, 3.3x the time)."""
        from repaint_nerf.core.render.renderer import RenderOptions

        return RenderOptions(max_samples=self.header.max_samples, **kw)


def open_trained(workspace: str | Path | Workspace, device: torch.device | str | None = None,
                 need_features: bool = False) -> Trained:
    """Open a workspace's current field (eval mode) with its scene as trained; `need_features` first checks
    that the field has a feature head."""
    ws = workspace if isinstance(workspace, Workspace) else Workspace.open(workspace)
    path = trained_path(ws)
    if need_features:
        require_feature_head(read_header(path), path)
    fld, grid, header = restore_field(Checkpoint.load(path), device)
    return Trained(ws, workspace_scene(ws, header.scene), fld, grid, header, path)


@dataclass
class LoadAs:
    """How to load the scene of a new reconstruction; saved in the workspace's settings for every later open."""

    downscale: float = 1.0
    kind: str | None = None  # None: the dataset's, else detected from the camera layout
    max_size: int = DEFAULT_MAX_SIZE  # photos' long side is capped to this (0: full size)
    sharpness_discard: float | None = None  # transforms JSONs: drop blurry frames (None: the file's own threshold)


@dataclass
class Teachers:
    """Which stage-1 teachers to distil (paper Eq. s1); None picks the workspace's saved choice."""

    features: bool = True
    depth: bool = True
    feature_model: str | None = None  # a model path / id, or a built-in name (stage1_targets.NAMED_FEATURES)
    feature_size: tuple[int, int] | None = None  # (H, W)
    feature_norm: str | None = None
    depth_model: str | None = None  # an ONNX path or 'none'


@dataclass
class Reconstruction:
    """A stage-1 trainer on a workspace, ready to train: what `start_reconstruction` returns."""

    workspace: Workspace
    scene: Scene
    trainer: Stage1Trainer
    resumed: bool  # the checkpoint's training state was loaded
    notes: list[str] = field(default_factory=list)


def _workspace_for(data: Path | None, workspace: str | Path | None, load_as: LoadAs | None,
                   resume: bool) -> tuple[Workspace, Path, dict]:
    """(workspace, scene path, the load settings this run asks for, to save once the scene has loaded): an existing
    workspace names its scene; data gets one beside it by default. A resumed run that does not name a sharpness
    threshold keeps the one the workspace was trained with (it chose the training images)."""
    if data is None or is_workspace(data):
        ws = Workspace.open(data if data is not None else workspace)
        return ws, scene_root(ws), {}
    if not data.exists():
        raise UserError("no such dataset, photo folder or workspace", data,
                        hint="check the path, or open the demo scene")
    ws = Workspace.open_or_create(workspace if workspace else default_workspace(data))
    key = str(data.resolve())
    old = ws.settings.get("scene")
    if old and old != key and (ws.original_version is not None or ws.current_version is not None):
        raise WorkspaceError(f"this workspace holds a reconstruction of another scene ({old})", ws.root,
                             hint="pass another --workspace folder")
    chosen: dict = {"scene": key}
    if load_as is not None:
        sharpness = load_as.sharpness_discard
        if sharpness is None and resume:
            sharpness = ws.settings.get("sharpness_discard")
        chosen.update(downscale=load_as.downscale, kind=load_as.kind, max_size=load_as.max_size,
                      sharpness_discard=sharpness)
    return ws, data, chosen


def check_training_frames(ws: Workspace, scene: Scene, header: CheckpointHeader) -> None:
    """Raise a WorkspaceError when `scene` would resume the workspace's checkpoint on other training images than it
    was trained on (another --sharpness-discard, photos added or removed): the field's appearance codes, one per
    training image in order, would belong to other photos. The images are those saved under TRAIN_FRAMES; a
    workspace from before that was saved is checked by the count of its codes."""
    names = list(scene.train.names)
    saved = ws.settings.get(TRAIN_FRAMES)
    codes = header.field_cfg().appearance_count if header.field_cfg().appearance_dim > 0 else 0
    if saved is not None and list(saved) == names or saved is None and codes in (0, len(names)):
        return
    if saved is None:
        what = f"its field has appearance codes for {codes} training images, this load gives {len(names)}"
    else:
        gone, new = [n for n in saved if n not in set(names)], [n for n in names if n not in set(saved)]
        what = f"it was trained on {len(saved)} training images, this load gives {len(names)}"
        what += "".join(f"; {label} {len(v)} (e.g. {v[0]})" for label, v in (("left out", gone), ("new", new)) if v)
        if not gone and not new:
            what += " in another order"
    sharp = ws.settings.get("sharpness_discard")
    raise WorkspaceError(f"cannot resume: the training images changed ({what}), so the per-image appearance codes "
                         f"and the training state would belong to other photos", ws.root,
                         hint=f"resume with the selection it was trained with (--sharpness-discard "
                              f"{'left out' if sharp is None else sharp}, the same photos), or train into a new "
                              f"--workspace")


def start_reconstruction(data: str | Path | None, workspace: str | Path | None = None, *,
                         train_cfg: TrainConfig | None = None, prefer_saved_config: bool = True,
                         teachers: Teachers | None = None, load_as: LoadAs | None = None,
                         device: torch.device | str | None = None, resume: bool = True,
                         at_current_version: bool = True) -> Reconstruction:
    """A stage-1 trainer for a dataset, photo folder or workspace (`data`; None: `workspace`).

    A dataset's workspace defaults to a folder beside it. With `resume`, the checkpoint's training state is
    loaded and the saved field config (and train config, when `prefer_saved_config`) is used; with
    `at_current_version` the field is the workspace's current version (an edit, or a version without a
    checkpoint), as the editor shows it. Teachers follow `teachers`, else the workspace's saved choices.
    """
    from repaint_nerf.core.teachers.stage1_targets import FEATURE_DIMS, depth_priors, feature_stream

    device = device if isinstance(device, torch.device) else get_device(device)
    ws, scene_path, chosen = _workspace_for(Path(data) if data is not None else None, workspace, load_as, resume)
    settings = {**ws.settings, **chosen}
    scene = _load_with_settings(scene_path, ws, settings.get("kind"), settings)  # a photo folder's SfM is cached there
    header = saved_header(ws) if resume else None
    if header is not None:
        check_training_frames(ws, scene, header)  # before the settings change: a refused run leaves them as they were
    ws.update_settings(**chosen, **{TRAIN_FRAMES: list(scene.train.names)})
    field_cfg = header.field_cfg() if header else None
    if header and prefer_saved_config and header.train_cfg() is not None:
        train_cfg = header.train_cfg()
    if header and header.scene and header.scene.normalization() is not None:
        scene.norm = header.scene.normalization()
    teachers = teachers or Teachers()
    notes: list[str] = []
    features = None
    if teachers.features and (field_cfg is None or field_cfg.feature_dim > 0):
        features = feature_stream(scene, ws, (field_cfg.feature_dim if field_cfg else 0) or FEATURE_DIMS,
                                   model=teachers.feature_model, input_size=teachers.feature_size,
                                   norm=teachers.feature_norm, notes=notes)
    depth = depth_priors(scene, ws, notes, model=teachers.depth_model) if teachers.depth else None
    trainer = Stage1Trainer(scene, ws, train_cfg, field_cfg, device=device, feature_targets=features,
                            depth_priors=depth)
    resumed = trainer.resume() if resume else False
    version = ws.current_version
    if at_current_version and version is not None and (version.kind == "edit" or not resumed):
        trainer.load_version(ws.version_path(version))
    return Reconstruction(ws, scene, trainer, resumed, notes)

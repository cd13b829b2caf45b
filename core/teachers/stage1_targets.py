"""What stage 1 distils besides colour (paper Eq. s1): teacher feature codes and depth priors of a scene's
training images, computed once and cached in the workspace. The editor and `repaint-nerf train` both call
these, so a workspace from either can be selected in.

Which teachers: an explicit model (a `train` flag), else the workspace's saved choice, else the
environment ($REPAINT_NERF_FEATURE_MODEL / $REPAINT_NERF_DEPTH_MODEL, or features.onnx / depth.onnx or a
feature / depth folder under $REPAINT_NERF_MODELS), else the weight-free default feature teacher and sparse
depth only. A model is an ONNX file or a transformers folder or cached model id (DINOv2, CLIP, SigLIP;
DPT, Depth Anything), told apart by config.json's model_type (core.models.paths.model_type). The choice is
saved in settings.json, so re-opening a workspace distils (and reads the cache of) the same teachers.
"""
from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

from repaint_nerf.core.errors import ModelNotFoundError, UserError, WorkspaceError

DEPTH_CACHE = "depth_priors.safetensors"
FEATURE_DIMS = 12
FEATURE_SETTING = "feature_model"  # null: the default teacher; else {"path", "input_size", "norm"}
DEPTH_SETTING = "depth_model"      # null: sparse priors only; else the model's path or cached model id
DEFAULT_FEATURE = "default"        # `--feature-model default`: back to the built-in teacher
LITE_FEATURE = "efficientnet-lite0"  # the packaged ImageNet network (the `lite` extra; core.teachers.feature_lite)
LITE_BLEND = LITE_FEATURE + "+" + DEFAULT_FEATURE  # its features concatenated with the built-in teacher's
NAMED_FEATURES = (DEFAULT_FEATURE, LITE_FEATURE, LITE_BLEND)  # teachers chosen by name, not by a path
NO_DEPTH_MODEL = "none"            # `--depth-model none`: sparse priors only
FEATURE_NORMS = ("imagenet", "clip")
ROOT_ENV = "REPAINT_NERF_MODELS"


@dataclass(frozen=True)
class FeatureModel:
    """A workspace's feature teacher: an ONNX file or a transformers folder / cached model id, with its input
    size (H, W) and (ONNX only) input normalisation, or the default teacher (path None)."""

    path: str | None = None
    input_size: tuple[int, int] | None = None
    norm: str = "imagenet"

    def to_setting(self) -> dict | None:
        """The settings.json value (None for the default teacher)."""
        if self.path is None:
            return None
        return {"path": self.path, "input_size": None if self.input_size is None else list(self.input_size),
                "norm": self.norm}

    @staticmethod
    def from_setting(value, where: Path) -> "FeatureModel":
        """Read the settings.json value back; a malformed one is a WorkspaceError naming the file."""
        if value is None:
            return FeatureModel()
        try:
            size = value.get("input_size")
            size = None if size is None else (int(size[0]), int(size[1]))
            return FeatureModel(str(value["path"]), size, check_norm(value.get("norm", "imagenet")))
        except (AttributeError, KeyError, TypeError, ValueError, IndexError, UserError):
            raise WorkspaceError(f"settings.json '{FEATURE_SETTING}' is not a feature model record ({value!r})",
                                 where, hint="fix it, or choose again with repaint-nerf train --feature-model "
                                             "PATH.onnx (or --feature-model default)") from None

    @property
    def label(self) -> str:
        return DEFAULT_FEATURE if self.path is None else Path(self.path).name


def check_norm(norm: str) -> str:
    """The name of a known input normalisation (imagenet or clip), else a UserError."""
    if norm not in FEATURE_NORMS:
        raise UserError(f"unknown feature normalisation {norm!r}", hint=f"use one of: {', '.join(FEATURE_NORMS)}")
    return norm


def norm_constants(norm: str) -> tuple[tuple, tuple]:
    """(mean, std) of a normalisation: ImageNet's, or CLIP's (core.models.clip) for CLIP-space models."""
    from repaint_nerf.core.teachers.feature_onnx import IMAGENET_MEAN, IMAGENET_STD

    if check_norm(norm) == "clip":
        from repaint_nerf.core.models.clip import CLIP_MEAN, CLIP_STD

        return CLIP_MEAN, CLIP_STD
    return IMAGENET_MEAN, IMAGENET_STD


def _trained(ws) -> bool:
    """Whether the workspace already holds a field (a checkpoint or a version)."""
    return any(Path(ws.checkpoints_dir).glob("*.safetensors")) or ws.current_version is not None


def _env_model(env: str, *root_names: str) -> str | None:
    """A model path from `env`, else the first of `root_names` under $REPAINT_NERF_MODELS that exists."""
    if os.environ.get(env):
        return os.environ[env]
    root = os.environ.get(ROOT_ENV)
    for name in root_names if root else ():
        if (Path(root).expanduser() / name).exists():
            return str(Path(root).expanduser() / name)
    return None


def _saved_value(value: str, teacher) -> str:
    """What settings.json keeps of a model value: the model's absolute path for a local path (a relative
    path or an ONNX folder reads the same later), the id itself for a cached model id."""
    return str(teacher.path.resolve()) if Path(value).expanduser().exists() else str(value)


_SOURCES = {"flag": "the {flag} flag", "env": "${env} (or $" + ROOT_ENV + ")",
            "setting": "the workspace setting '{setting}'"}


def _locate(kind: str, value: str, source: str) -> tuple[Path, str]:
    """(local file or folder, 'onnx' or config.json's model_type) of a model value (a path or cached id)."""
    from repaint_nerf.core.models.paths import locate_model, model_kind, model_type

    k = model_kind(kind)
    where = _SOURCES.get(source, _SOURCES["flag"]).format(flag=k.flag, env=k.env, setting=k.settings_key)
    path = locate_model(kind, value, where)
    return path, model_type(path)


def choose_feature_model(ws, model: str | None = None, input_size: tuple[int, int] | None = None,
                         norm: str | None = None) -> tuple[FeatureModel, str]:
    """(choice, source): `model` ('default' or a path) > the workspace's saved choice > the environment >
    `default_feature_model()`. `input_size` / `norm` override those of the chosen ONNX model. A workspace
    trained before choices were saved keeps the built-in teacher it was trained with."""
    from repaint_nerf.core.teachers.feature_onnx import ENV_FEATURE_MODEL

    settings = ws.settings
    if model:
        choice = FeatureModel() if model == DEFAULT_FEATURE else FeatureModel(str(model)), "flag"
    elif FEATURE_SETTING in settings:
        choice = FeatureModel.from_setting(settings[FEATURE_SETTING], ws.root / "settings.json"), "setting"
    elif _trained(ws):
        choice = FeatureModel(), "default"
    elif not _env_model(ENV_FEATURE_MODEL, "features.onnx", "feature"):
        choice = default_feature_model(), "default"
    else:
        choice = FeatureModel(_env_model(ENV_FEATURE_MODEL, "features.onnx", "feature")), "env"
    fm, source = choice
    if (input_size is not None or norm is not None) and (fm.path is None or source == "default"):
        raise UserError("--feature-size and --feature-norm describe a feature model, and none is chosen",
                        hint="pass --feature-model PATH.onnx / FOLDER / MODEL_ID too "
                             "(or set REPAINT_NERF_FEATURE_MODEL)")
    if fm.path is not None:
        fm = FeatureModel(fm.path, input_size if input_size is not None else fm.input_size,
                          check_norm(norm if norm is not None else fm.norm))
    return fm, source


def default_feature_model() -> FeatureModel:
    """The teacher a new workspace distils when nothing names one: EfficientNet-Lite0 blended with the built-in
    teacher where the `lite` extra is installed, else the built-in teacher. The blend's masks are better on
    scenes not designed around either teacher, a training step costs the same, and its features are computed
    beside training (core.teachers.feature_stream), so it delays no first step (docs/MODELS.md)."""
    from repaint_nerf.core.teachers.feature_lite import available

    return FeatureModel(LITE_BLEND) if available() else FeatureModel()


def saved_feature_name(settings: dict) -> str | None:
    """The feature teacher a workspace's settings name ('default', a built-in name, or a model path / id), for
    the editor to show; None when it has not chosen one yet (or the record is malformed: opening says why)."""
    if FEATURE_SETTING not in settings:
        return None
    value = settings[FEATURE_SETTING]
    if value is None:
        return DEFAULT_FEATURE
    return str(value["path"]) if isinstance(value, dict) and value.get("path") else None


def feature_choices(*current: str | None) -> list[str]:
    """The feature teachers the editor offers: the built-in one, the lite ones only when the `lite` extra is
    installed (its packages are found, not imported), then each of `current` (a workspace's saved model
    path or id, the editor's last pick) that is none of those, so a choice made elsewhere still shows."""
    from repaint_nerf.core.teachers.feature_lite import available

    names = [DEFAULT_FEATURE] + ([LITE_FEATURE, LITE_BLEND] if available() else [])
    for name in current:
        if name and name not in names:
            names.append(name)
    return names


def named_feature_teacher(name: str):
    """The teacher of a built-in name ('default', 'efficientnet-lite0', 'efficientnet-lite0+default'); the lite
    ones raise a ModelNotFoundError naming the pip command when the `lite` extra is not installed."""
    from repaint_nerf.core.teachers.feature_default import DefaultFeatureTeacher

    if name == DEFAULT_FEATURE:
        return DefaultFeatureTeacher()
    from repaint_nerf.core.teachers.feature_lite import LiteFeatureTeacher

    if name == LITE_FEATURE:
        return LiteFeatureTeacher()
    if name == LITE_BLEND:
        from repaint_nerf.core.teachers.feature_blend import BlendFeatureTeacher

        return BlendFeatureTeacher([(LiteFeatureTeacher(), 0.5), (DefaultFeatureTeacher(), 0.5)])
    raise ValueError(f"unknown built-in feature teacher {name!r}; known: {', '.join(NAMED_FEATURES)}")


def make_feature_teacher(fm: FeatureModel, source: str = "flag"):
    """The teacher of a choice (a built-in name, ONNX, or a transformers backbone: DINOv2, CLIP as MaskCLIP,
    SigLIP); a missing or broken model is a ModelNotFoundError naming what to fix."""
    from repaint_nerf.core.teachers.feature_hf import HFFeatureTeacher
    from repaint_nerf.core.teachers.feature_onnx import OnnxFeatureTeacher

    if fm.path is None:
        return named_feature_teacher(DEFAULT_FEATURE)
    try:
        if fm.path in NAMED_FEATURES:
            return named_feature_teacher(fm.path)
        path, kind = _locate("feature", fm.path, source)
        if kind != "onnx":  # a transformers model brings its own input normalisation
            return HFFeatureTeacher(path, input_size=fm.input_size, label=fm.path)
        mean, std = norm_constants(fm.norm)
        return OnnxFeatureTeacher(path, input_size=fm.input_size, mean=mean, std=std)
    except ModelNotFoundError as exc:
        if source != "setting":
            raise
        raise ModelNotFoundError(f"the workspace's feature model (settings.json '{FEATURE_SETTING}') cannot be "
                                 f"used: {str(exc).splitlines()[0]}",
                                 hint="move the model back, or choose again: repaint-nerf train SCENE --workspace "
                                      "WS --feature-model PATH.onnx|FOLDER|MODEL_ID (or --feature-model "
                                      "default)") from exc


def workspace_feature_teacher(ws):
    """The feature teacher a workspace was trained with (its saved choice), for queries against its field."""
    return make_feature_teacher(*choose_feature_model(ws))


def feature_stream(scene, ws, dims: int = FEATURE_DIMS, model: str | None = None,
                   input_size: tuple[int, int] | None = None, norm: str | None = None, notes: list | None = None):
    """Teacher feature codes of the training images, computed on a background thread and cached under the
    workspace's teachers/ (core.teachers.feature_stream): stage 1 trains colour meanwhile. The teacher is built
    here, so a missing or broken model fails before any work, and then saved in the settings."""
    from repaint_nerf.core.teachers.feature_stream import FeatureStream

    fm, source = choose_feature_model(ws, model, input_size, norm)
    teacher = make_feature_teacher(fm, source)
    if fm.path is not None:
        fm = FeatureModel(_saved_value(fm.path, teacher), fm.input_size, fm.norm)
    old = ws.settings.get(FEATURE_SETTING, "unset")
    if notes is not None and old != "unset" and old != fm.to_setting():
        notes.append(f"feature teacher changed to {fm.label}: the feature field now learns it (select again)")
    stream = FeatureStream(scene.train.images, teacher, ws.teachers_dir, dims=dims)
    ws.update_settings(**{FEATURE_SETTING: fm.to_setting(), "teacher": getattr(teacher, "name", DEFAULT_FEATURE),
                          "feature_dims": int(dims)})
    return stream


def feature_targets(scene, ws, dims: int = FEATURE_DIMS, model: str | None = None,
                    input_size: tuple[int, int] | None = None, norm: str | None = None,
                    notes: list | None = None):
    """Teacher feature codes of the training images, all of them (`feature_stream`, waited for)."""
    return feature_stream(scene, ws, dims, model, input_size, norm, notes).wait().codes


def workspace_codec(scene, ws, teacher):
    """The PCA codec of the workspace's feature cache for `teacher` (rebuilt from the images when the cache
    is gone): what projects a teacher-space query into the field's feature codes."""
    from repaint_nerf.core.teachers.cache import build_feature_store, stored_codec

    dims = int(ws.settings.get("feature_dims", FEATURE_DIMS))
    codec = stored_codec(scene.train.images, teacher, ws.teachers_dir, dims=dims)
    if codec is None:
        codec = build_feature_store(scene.train.images, teacher, ws.teachers_dir, dims=dims).codec
    return codec


def choose_depth_model(ws, model: str | None = None) -> tuple[str | None, str]:
    """(model path / cached id, or None for sparse only; source): `model` ('none' or a model) > the saved
    choice > the environment. A workspace trained before choices were saved keeps its sparse priors."""
    from repaint_nerf.core.teachers.depth_onnx import ENV_DEPTH_MODEL

    if model:
        return (None if model == NO_DEPTH_MODEL else str(model)), "flag"
    settings = ws.settings
    if DEPTH_SETTING in settings:
        return (str(settings[DEPTH_SETTING]) if settings[DEPTH_SETTING] else None), "setting"
    env = _env_model(ENV_DEPTH_MODEL, "depth.onnx", "depth")
    return (env, "env") if env and not _trained(ws) else (None, "none")


def make_depth_teacher(path: str, source: str = "flag"):
    """The monocular depth teacher of a model (ONNX, or a transformers DPT / Depth Anything); a missing or
    broken model names what to fix."""
    from repaint_nerf.core.teachers.depth_hf import HFDepthTeacher
    from repaint_nerf.core.teachers.depth_onnx import OnnxDepthTeacher

    try:
        located, kind = _locate("depth", path, source)
        return OnnxDepthTeacher(located) if kind == "onnx" else HFDepthTeacher(located)
    except ModelNotFoundError as exc:
        if source != "setting":
            raise
        raise ModelNotFoundError(f"the workspace's depth model (settings.json '{DEPTH_SETTING}') cannot be used: "
                                 f"{str(exc).splitlines()[0]}",
                                 hint="move the model back, or choose again: repaint-nerf train SCENE --workspace "
                                      "WS --depth-model PATH.onnx|FOLDER|MODEL_ID (or --depth-model none)") from exc


def depth_priors(scene, ws, notes: list | None = None, model: str | None = None):
    """Depth priors of the training images, cached in the workspace: sparse (SfM points, else triangulated
    from the known poses), made dense by a monocular depth model aligned to them when one is chosen. None
    (with a line in `notes`) when too few matches exist: stage 1 then trains without depth."""
    path, source = choose_depth_model(ws, model)
    teacher = make_depth_teacher(path, source) if path else None  # a broken model fails before any work
    sparse = sparse_depth_priors(scene, ws, notes)
    if teacher is not None and sparse is None and notes is not None:
        notes.append(f"depth model {Path(path).name} not used: there are no sparse depth points to align it to")
    ws.update_settings(**{DEPTH_SETTING: None if teacher is None else _saved_value(path, teacher)})
    if teacher is None or sparse is None:
        return sparse
    return _cached_priors(scene, ws.teachers_dir / _aligned_cache_name(teacher),
                          lambda: _aligned(teacher, scene, sparse))


def _aligned(teacher, scene, sparse):
    from repaint_nerf.core.teachers.depth_onnx import aligned_monocular_depth

    return aligned_monocular_depth(teacher, scene.train.images, sparse)


def _aligned_cache_name(teacher) -> str:
    """The cache file of one depth model's aligned depth: keyed by the model's config, so another model (or
    the same name with other settings) never reads it."""
    from repaint_nerf.core.teachers.cache import teacher_key

    return f"depth_priors-{teacher_key(teacher)}.safetensors"


def sparse_depth_priors(scene, ws, notes: list | None = None):
    """Sparse depth priors, cached; None (with a line in `notes`) when too few matches exist."""
    from repaint_nerf.core.teachers.depth_sparse import depth_for_scene

    try:
        return _cached_priors(scene, ws.teachers_dir / DEPTH_CACHE, lambda: depth_for_scene(scene))
    except (UserError, ValueError, RuntimeError) as exc:
        if notes is not None:
            notes.append(f"no depth priors ({str(exc).splitlines()[0]})")
        return None


def _cached_priors(scene, path: Path, compute):
    """Priors read from `path` when it holds one per training image, else computed and saved there."""
    from repaint_nerf.core.teachers.depth import DepthPriors

    if path.exists():
        try:
            priors = DepthPriors.load(path)
            if len(priors) == len(scene.train):
                return priors
        except UserError:
            pass
    priors = compute()
    priors.save(path)
    return priors

"""What stage 1 distils besides colour (paper Eq. s1): default-teacher feature codes and sparse depth priors
of a scene's training images, computed once and cached in the workspace. The editor and `repaint-nerf train`
both call these, so a workspace from either can be selected in."""
from __future__ import annotations

from core.errors import UserError

DEPTH_CACHE = "depth_priors.safetensors"
FEATURE_DIMS = 12


def feature_targets(scene, ws, dims: int = FEATURE_DIMS):
    """Default-teacher feature codes of the training images (cached under the workspace's teachers/)."""
    from core.teachers.cache import build_feature_store
    from core.teachers.feature_default import DefaultFeatureTeacher

    teacher = DefaultFeatureTeacher()
    store = build_feature_store(scene.train.images, teacher, ws.teachers_dir, dims=dims)
    ws.update_settings(teacher=getattr(teacher, "name", "default"))
    return store.codes


def depth_priors(scene, ws, notes: list | None = None):
    """Sparse depth priors (SfM points, else triangulated from the known poses), cached in the workspace;
    None (with a line in `notes`) when too few matches exist: stage 1 then trains without depth."""
    from core.teachers.depth import DepthPriors
    from core.teachers.depth_sparse import depth_for_scene

    path = ws.teachers_dir / DEPTH_CACHE
    if path.exists():
        try:
            priors = DepthPriors.load(path)
            if len(priors) == len(scene.train):
                return priors
        except UserError:
            pass
    try:
        priors = depth_for_scene(scene)
    except (UserError, ValueError, RuntimeError) as exc:
        if notes is not None:
            notes.append(f"no depth priors ({str(exc).splitlines()[0]})")
        return None
    priors.save(path)
    return priors

"""What `repair` rebuilds rather than keeps: a selection's masks (from the saved selection and the current field)
and the teacher caches (from the photos), through the same functions that made them. Needs the workspace's
scene; when it cannot be loaded, one line says what is left to do."""
from __future__ import annotations

from repaint_nerf.core.errors import UserError


def _recompute_masks(trained) -> str:
    """The saved selection's masks of every training view, written into WS/masks as `select` writes them."""
    import torch

    from repaint_nerf.core.select.masks import ViewCache, masks_for_views
    from repaint_nerf.core.select.selection import Selection

    ws, scene = trained.workspace, trained.scene
    try:
        sel = Selection.load(ws)
    except UserError:
        return "masks: not recomputed: there is no readable selection (select again: repaint-nerf select WS ...)"
    cams = scene.field_cameras("train")
    with torch.no_grad():
        masks = masks_for_views(trained.field, trained.grid, cams, sel, workspace=ws,
                                cache=ViewCache(trained.field, trained.grid, cams,
                                                render_opts=trained.render_options()),
                                names=list(scene.train.names or []) or None, images=scene.train.images)
    return f"masks: recomputed {len(masks)} view(s) from selections/current.json"


def _recompute_teachers(trained) -> str:
    """The feature and depth caches of the training photos (what stage-1 training reads)."""
    from repaint_nerf.core.teachers.stage1_targets import FEATURE_DIMS, depth_priors, feature_targets

    ws, scene = trained.workspace, trained.scene
    done = []
    if trained.header.feature_dim > 0:
        feature_targets(scene, ws, int(ws.settings.get("feature_dims", FEATURE_DIMS)))
        done.append("features")
    if depth_priors(scene, ws) is not None:
        done.append("depth")
    return f"teachers: recomputed the {' and '.join(done) or 'no'} cache(s) from the photos"


def recompute_missing(ws, todo: set[str]) -> list[str]:
    """Recompute what `repair` set aside (`todo` holds 'masks' and/or 'teachers'); one line per outcome."""
    from repaint_nerf.core.session import open_trained

    try:
        trained = open_trained(ws, "cpu")
    except UserError as exc:
        return [f"{what}: not recomputed ({str(exc).splitlines()[0]}); run repair again once the scene is back"
                for what in sorted(todo)]
    out = []
    if "teachers" in todo:
        out.append(_recompute_teachers(trained))
    if "masks" in todo:
        out.append(_recompute_masks(trained))
    return out

"""Per-view refinement of selection masks with Segment Anything: each view's mask (from the feature
field) gives SAM a box and a point prompt, and SAM's mask, which follows the image's edges, replaces it.
The refined masks are then distilled as the field's own are."""
from __future__ import annotations

import os
from typing import Callable, Sequence

import cv2
import numpy as np
import torch

from repaint_nerf.core.teachers.base import check_image

BOX_MARGIN = 0.1     # SAM's mask is kept inside the prompt box grown by this fraction of its size per side
MIN_AGREEMENT = 0.25  # below this IoU with the field's mask SAM is taken to have missed, and the mask is kept
SAM_SETTING = "sam_path"  # null or absent: no refinement; else the SAM model's path or cached model id
OFF = "none"              # `--sam-path none`: refinement off for the workspace


def mask_prompt(mask: np.ndarray) -> tuple[tuple[int, int, int, int], tuple[int, int]] | None:
    """(box x0, y0, x1, y1 (exclusive), point x, y) of a mask's largest connected region: its bounding box and
    its most interior pixel (the distance-transform peak). None for an empty mask."""
    m = np.asarray(mask, bool).astype(np.uint8)
    if not m.any():
        return None
    n, labels, stats, _ = cv2.connectedComponentsWithStats(m, connectivity=8)
    big = 1 + int(np.argmax(stats[1:, cv2.CC_STAT_AREA]))
    x, y, w, h = (int(v) for v in stats[big, :4])
    region = np.pad((labels == big).astype(np.uint8), 1)
    dist = cv2.distanceTransform(region, cv2.DIST_L2, 5)[1:-1, 1:-1]
    py, px = np.unravel_index(int(np.argmax(dist)), dist.shape)
    return (x, y, x + w, y + h), (int(px), int(py))


def grown_box(box: tuple[int, int, int, int], height: int, width: int, margin: float = BOX_MARGIN) -> np.ndarray:
    """A bool (height, width) map of `box` grown by `margin` of its size on every side (clipped to the image)."""
    x0, y0, x1, y1 = box
    mx, my = int(np.ceil(margin * (x1 - x0))), int(np.ceil(margin * (y1 - y0)))
    out = np.zeros((height, width), bool)
    out[max(0, y0 - my):min(height, y1 + my), max(0, x0 - mx):min(width, x1 + mx)] = True
    return out


def _iou(a: np.ndarray, b: np.ndarray) -> float:
    union = np.count_nonzero(a | b)
    return np.count_nonzero(a & b) / union if union else 1.0


@torch.no_grad()
def sam_mask(image: np.ndarray, box: tuple[int, int, int, int], point: tuple[int, int], sam) -> np.ndarray:
    """SAM's mask (bool (H, W)) of one image for a box and a positive point prompt: of its three candidate
    masks, the one SAM scores highest."""
    rgb = check_image(image)
    inputs = sam.processor(images=rgb, input_boxes=[[[float(v) for v in box]]],
                           input_points=[[[[float(point[0]), float(point[1])]]]], input_labels=[[[1]]],
                           return_tensors="pt")
    inputs = {k: v.to(sam.device) if isinstance(v, torch.Tensor) else v for k, v in inputs.items()}
    out = sam.model(pixel_values=inputs["pixel_values"], input_points=inputs["input_points"],
                    input_labels=inputs["input_labels"], input_boxes=inputs["input_boxes"], multimask_output=True)
    masks = sam.processor.post_process_masks(out.pred_masks.cpu(), inputs["original_sizes"].cpu(),
                                             inputs["reshaped_input_sizes"].cpu())[0]
    scores = out.iou_scores.reshape(-1).float().cpu()
    return np.asarray(masks.reshape(-1, *rgb.shape[:2])[int(torch.argmax(scores))], bool)


def refine_masks(images: Sequence[np.ndarray], masks: Sequence[np.ndarray], model,
                 min_agreement: float = MIN_AGREEMENT) -> list[np.ndarray]:
    """Each view's mask refined by SAM (`model`: core.models.sam.Sam) prompted with that mask's box and
    interior point; SAM's mask is clipped to the grown box, and a view keeps its mask when SAM's IoU with it
    is under `min_agreement` (SAM missed) or the mask is empty. Returns bool masks of the same shapes."""
    if len(images) != len(masks):
        raise ValueError(f"{len(images)} images but {len(masks)} masks")
    out = []
    for image, mask in zip(images, masks):
        mask = np.asarray(mask, bool)
        prompt = mask_prompt(mask)
        if prompt is None:
            out.append(mask.copy())
            continue
        if image.shape[:2] != mask.shape:
            image = cv2.resize(np.ascontiguousarray(image), (mask.shape[1], mask.shape[0]),
                               interpolation=cv2.INTER_AREA)
        box, point = prompt
        refined = sam_mask(image, box, point, model) & grown_box(box, *mask.shape)
        out.append(refined if _iou(refined, mask) >= min_agreement else mask.copy())
    return out


def workspace_refiner(ws, images: Sequence[np.ndarray], flag: str | None = None,
                      environ=None) -> Callable[[list[np.ndarray]], list[np.ndarray]] | None:
    """The mask refinement of a workspace: SAM from `flag` ('none' turns it off) > $REPAINT_NERF_SAM_PATH >
    $REPAINT_NERF_MODELS/sam > the workspace's 'sam_path' setting, bound to `images`; None when no SAM is
    chosen. A model given by the flag is saved in the settings once it loads."""
    from pathlib import Path

    from repaint_nerf.core.models.paths import ROOT_ENV, model_kind, resolve_model_path
    from repaint_nerf.core.models.sam import load_sam

    env = os.environ if environ is None else environ
    if flag == OFF:
        ws.update_settings(**{SAM_SETTING: None})
        return None
    root = env.get(ROOT_ENV)
    if not (flag or env.get(model_kind("sam").env) or ws.settings.get(SAM_SETTING)
            or (root and (Path(root).expanduser() / "sam").exists())):
        return None
    sam = load_sam(resolve_model_path("sam", flag, ws.settings, env))
    if flag:
        ws.update_settings(**{SAM_SETTING: str(Path(flag).expanduser().resolve()) if Path(flag).expanduser().exists()
                              else str(flag)})
    return lambda masks: refine_masks(images, masks, sam)

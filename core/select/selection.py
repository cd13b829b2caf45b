"""The Selection record: positive/negative patches with their views, their query vectors, text queries,
the threshold, the clean-up switch and the teacher the field learned from; saved into the workspace
atomically (WS/selections/<name>.json) so the editor, `select` and the repaint agree on one selection.
"""
from __future__ import annotations

import json
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch
from torch import Tensor

from repaint_nerf.core.errors import UserError, WorkspaceError
from repaint_nerf.core.select.masks import (DEFAULT_THRESHOLD, check_threshold, map_cameras, similarity_map,
                                            threshold_mask)
from repaint_nerf.core.select.geometry import DEFAULT_GEOMETRY, GEOMETRY_NAMES
from repaint_nerf.core.select.query import Patch, patch_query, text_query
from repaint_nerf.core.workspace import atomic, integrity

FORMAT_VERSION = 1


@dataclass
class Selection:
    """Queries that select an object; see `core.select.masks.similarity_map` for how several combine."""

    patches: list[Patch] = field(default_factory=list)
    positives: list[Tensor] = field(default_factory=list)  # (F,) query vectors, patches first then texts
    negatives: list[Tensor] = field(default_factory=list)
    texts: list[str] = field(default_factory=list)
    threshold: float = DEFAULT_THRESHOLD  # what the masks use: the automatic one unless the user chose one
    cleanup: bool = True
    geometry: str = DEFAULT_GEOMETRY  # the masks' geometry parts: 'basic' or 'full' (core.select.geometry.parts_named)
    auto_threshold: float | None = None  # the automatic threshold of the queries (core.select.autothreshold)
    anchors: list[list[float]] = field(default_factory=list)  # field-space surface points of free-view patches
    # the overlay's map (region_map) of the view the newest positive patch was drawn in; not saved
    patch_region: np.ndarray | None = field(default=None, repr=False, compare=False)
    teacher: str = ""
    created: float = field(default_factory=time.time)

    # -- building --------------------------------------------------------------------------------
    def add_patch(self, features: Tensor, patch, subtract: bool = False, view: int | None = None) -> Patch:
        """Add the mean feature of a patch of a rendered feature map (H, W, F) as a positive (or, with
        `subtract`, a negative) query. `patch` is a `Patch` in pixels, or a plain (x0, y0, x1, y1) in image
        fractions [0, 1] (the editor's drag) in view `view` (-1 when it is not a training view)."""
        features = torch.as_tensor(features)
        h, w = int(features.shape[0]), int(features.shape[1])
        if isinstance(patch, Patch):
            p = Patch(patch.view, patch.x0, patch.y0, patch.x1, patch.y1, patch.positive and not subtract)
        else:
            p = Patch.from_normalized(patch, -1 if view is None else view, w, h, positive=not subtract)
        q = patch_query(features, p)
        self._check_dim(q)
        (self.positives if p.positive else self.negatives).append(q.cpu())
        self.patches.append(p)
        return p

    def add_anchors(self, points) -> None:
        """Keep the field-space surface points (N, 3) of a positive patch drawn outside the training views
        (core.select.geometry.patch_anchors): they seed the training views' masks as a training-view patch does."""
        self.anchors.extend(np.round(np.asarray(points, np.float64).reshape(-1, 3), 5).tolist())

    def anchor_patch(self, similarity: np.ndarray, patch, depth: np.ndarray, opacity: np.ndarray, camera,
                     edge_depth: np.ndarray | None = None) -> float:
        """For a positive patch drawn in a view that is not a training view (the editor's free camera, `camera` at
        the maps' size): its automatic threshold in that view (kept as `auto_threshold`; its region stops at the
        edges of `edge_depth`, else of `depth`: masks.ViewMaps) and its surface points on `depth` at that
        threshold (kept as anchors). Returns the threshold."""
        from repaint_nerf.core.select.autothreshold import (level_similarity, patch_auto_threshold_px, patch_pixels,
                                                            uses_edges)
        from repaint_nerf.core.select.geometry import patch_anchors

        edges_on = depth if edge_depth is None else edge_depth
        sim = np.asarray(similarity, np.float32)
        px = patch_pixels(sim.shape, patch)
        picked = patch_auto_threshold_px(sim, px, edges_on, opacity, edges=uses_edges(self))
        auto = self.auto_threshold = picked.value
        self.patch_region = level_similarity(sim, picked.levels)  # grown from the patch, as its threshold was
        self.add_anchors(patch_anchors(px, similarity, depth, opacity, camera, auto))
        return auto

    def refine_auto_threshold(self, own: float, maps: list, cameras) -> float:
        """The automatic threshold of a free-view patch (`own`, what `anchor_patch` returned) refined by training
        views that see its anchors (`maps`: their ViewMaps; `cameras`: those views at the maps' size, e.g. the
        ones `geometry.anchor_views` chose): each grows its region from the anchors it sees, and the leaking ones
        vote (`autothreshold.views_threshold`). Kept as `auto_threshold`; returned."""
        from repaint_nerf.core.select.autothreshold import views_threshold

        self.auto_threshold = views_threshold(own, self._voters(self.anchor_points(), maps, cameras))
        return self.auto_threshold

    def training_views_threshold(self, own: float, similarity: np.ndarray, seeds: np.ndarray, cache, view: int
                                 ) -> float:
        """The automatic threshold of patches drawn in training view `view` (pixels `seeds`, bool (H, W) of that
        view's maps in `cache`, a masks.ViewCache, whose `similarity` to the selection the caller has) whose own
        region shows no leak (`own`: that view's value): the
        training views that see the patches' surface points at `own` (up to `geometry.VOTE_VIEWS`) grow their
        regions from them and vote where none of them leaks (`autothreshold.walled_views_threshold`)."""
        from repaint_nerf.core.select.autothreshold import walled_views_threshold
        from repaint_nerf.core.select.geometry import anchor_views, patch_anchors

        maps = cache.get(view)
        cams = cache.cameras.to("cpu")
        points = patch_anchors(seeds, similarity, maps.depth.numpy(), maps.opacity.numpy(), cams[view:view + 1], own)
        voters = [i for i in anchor_views(points, cams) if i != view]
        if not voters:
            return float(own)
        vm = [cache.mask_maps(i) for i in voters]  # the maps their masks will be shaped on
        others = self._voters(points, vm, map_cameras(cams[torch.tensor(voters, dtype=torch.long)], vm))
        return walled_views_threshold(own, others)

    def _voters(self, points: np.ndarray, maps: list, cameras) -> list:
        """The AutoThreshold of each view of `maps` (ViewMaps; `cameras` at their size) that sees one of `points`,
        its region grown from the pixels where it sees them."""
        from repaint_nerf.core.select.autothreshold import patch_auto_threshold_px, uses_edges
        from repaint_nerf.core.select.geometry import anchor_seeds

        return [patch_auto_threshold_px(self.similarity(maps[i].feature).float().numpy(), seeds,
                                        maps[i].edge_depth().numpy(), maps[i].opacity.numpy(),
                                        edges=uses_edges(self))
                for i, seeds in anchor_seeds(points, [m.depth.numpy() for m in maps], cameras)]

    def region_map(self, similarity: np.ndarray, depth: np.ndarray, opacity: np.ndarray, camera,
                   edge_depth: np.ndarray | None = None) -> np.ndarray | None:
        """This view's similarity kept where the region grown from the anchors it sees reaches
        (`autothreshold.region_similarity`; `depth`: its median z-depth, on which the anchors are seen; edges from
        `edge_depth`, else `depth`; `camera`: the view at the maps' size), for the editor's overlay: its slider then
        shows what the masks will hold. None when the view sees no anchor (a text query, the object out of view)."""
        from repaint_nerf.core.select.autothreshold import region_similarity, uses_edges
        from repaint_nerf.core.select.geometry import project_seeds

        if not len(self.anchors):
            return None
        seeds = project_seeds(self.anchor_points(), [np.asarray(depth, np.float32)], camera)[0]
        if not seeds.any():
            return None
        return region_similarity(similarity, seeds, depth if edge_depth is None else edge_depth, opacity,
                                 edges=uses_edges(self))

    def anchor_points(self) -> np.ndarray:
        """The anchors as a float32 (N, 3) array."""
        return np.asarray(self.anchors, np.float32).reshape(-1, 3)

    def add_text(self, text: str, teacher, codec=None) -> None:
        """Add a text query through a teacher with a CLIP-aligned text encoder (see query.text_query)."""
        q = text_query(text, teacher, codec)
        self._check_dim(q)
        self.positives.append(q)
        self.texts.append(str(text))

    def _check_dim(self, q: Tensor) -> None:
        have = self.positives + self.negatives
        if have and have[0].shape[-1] != q.shape[-1]:
            raise UserError(f"this query has {q.shape[-1]} feature dimensions, the selection's have "
                            f"{have[0].shape[-1]}", hint="start a new selection")

    @property
    def empty(self) -> bool:
        return not self.positives

    @property
    def feature_dim(self) -> int:
        return int(self.positives[0].shape[-1]) if self.positives else 0

    # -- using -------------------------------------------------------------------------------------
    def query_tensors(self, device=None) -> tuple[Tensor, Tensor | None]:
        """(positives (P, F), negatives (N, F) or None) on `device`."""
        if not self.positives:
            raise UserError("the selection has no positive patch", hint="select a patch on the object first")
        pos = torch.stack(self.positives).to(device)
        neg = torch.stack(self.negatives).to(device) if self.negatives else None
        return pos, neg

    def similarity(self, features: Tensor) -> Tensor:
        """Similarity map (H, W) of a rendered feature map (H, W, F) to this selection."""
        features = torch.as_tensor(features)
        pos, neg = self.query_tensors(features.device)
        return similarity_map(features, pos, neg)

    def mask(self, features: Tensor, threshold: float | None = None) -> Tensor:
        """Mask (H, W) bool: similarity > threshold (the selection's threshold by default)."""
        return threshold_mask(self.similarity(features), self.threshold if threshold is None else threshold)

    # -- saving ----------------------------------------------------------------------------------
    def to_dict(self) -> dict:
        return {"format": FORMAT_VERSION, "threshold": float(self.threshold), "cleanup": bool(self.cleanup),
                "geometry": self.geometry,
                "auto_threshold": None if self.auto_threshold is None else float(self.auto_threshold),
                "teacher": self.teacher, "created": self.created, "texts": list(self.texts),
                "patches": [p.to_dict() for p in self.patches], "anchors": self.anchors,
                "positives": [q.float().tolist() for q in self.positives],
                "negatives": [q.float().tolist() for q in self.negatives]}

    @staticmethod
    def from_dict(d: dict) -> "Selection":
        if d.get("format") != FORMAT_VERSION:
            raise ValueError(f"selection format {d.get('format')!r}, expected {FORMAT_VERSION}")
        anchors = [[float(x) for x in p] for p in d.get("anchors", [])]
        if any(len(p) != 3 for p in anchors):
            raise ValueError("an anchor point is not three numbers")
        geometry = str(d.get("geometry", "basic"))  # selections saved before it had the choice: basic
        if geometry not in GEOMETRY_NAMES:
            raise ValueError(f"unknown geometry {geometry!r}, expected one of {', '.join(GEOMETRY_NAMES)}")
        return Selection(patches=[Patch.from_dict(p) for p in d["patches"]],
                         positives=[torch.tensor(q, dtype=torch.float32) for q in d["positives"]],
                         negatives=[torch.tensor(q, dtype=torch.float32) for q in d["negatives"]],
                         texts=list(d.get("texts", [])), threshold=check_threshold(d["threshold"]),
                         cleanup=bool(d.get("cleanup", True)), geometry=geometry,
                         teacher=str(d.get("teacher", "")),
                         auto_threshold=None if d.get("auto_threshold") is None
                         else check_threshold(d["auto_threshold"]),
                         anchors=anchors,
                         created=float(d.get("created", 0.0)))

    def save(self, workspace, name: str = "current") -> Path:
        """Write the selection to WS/selections/<name>.json atomically, sealed with its content hash; returns the path."""
        path = Path(workspace.selections_dir) / f"{name}.json"
        atomic.write_sealed_json(path, self.to_dict())
        return path

    @staticmethod
    def load(workspace, name: str = "current") -> "Selection":
        """Read a selection written by `save`; a missing or damaged file is a WorkspaceError."""
        path = Path(workspace.selections_dir) / f"{name}.json"
        if not path.is_file():
            raise WorkspaceError("no selection saved here", path,
                                 hint="make one: repaint-nerf select WS --view I --patch x0,y0,x1,y1")
        try:
            text = path.read_text(encoding="utf-8")
            data = json.loads(text)
            if integrity.check_json_text(text, data) is False:
                raise ValueError("its content hash does not match: the file is damaged")
            return Selection.from_dict(data)
        except (OSError, ValueError, KeyError, TypeError, AttributeError) as exc:
            raise WorkspaceError(f"cannot read this selection ({exc})", path,
                                 hint=integrity.repair_hint(path, "make a new selection with repaint-nerf select")) from exc

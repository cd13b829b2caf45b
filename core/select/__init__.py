"""Selection through the feature field (paper, "Semantic Mask Extraction"): patch or text queries,
similarity maps, masks for every training view, 3D clean-up and the saved Selection record."""
from repaint_nerf.core.select.masks import (DEFAULT_THRESHOLD, ViewCache, load_masks, masks_for_views, similarity_map,
                               threshold_mask, write_masks)
from repaint_nerf.core.select.query import Patch, patch_query, text_query
from repaint_nerf.core.select.selection import Selection
from repaint_nerf.core.select.similarity import cosine_similarity, normalize

__all__ = ["DEFAULT_THRESHOLD", "Patch", "Selection", "ViewCache", "cosine_similarity", "load_masks",
           "masks_for_views", "normalize", "patch_query", "similarity_map", "text_query", "threshold_mask",
           "write_masks"]

"""The offline pose backbone (multi-view geometry that runs without learned multi-view weights).

* :mod:`.matching` -- pure helpers: matching, rays, triangulation, keypoint depths;
* :mod:`.context` -- one pass's inputs, the reconstruction record, the view memo;
* :mod:`.vote` -- the dense motion vote (moving pixels, chained older views);
* :mod:`.reconstruction` -- points on a depth prior, P3P placement, dense refinement;
* :mod:`.two_view` -- essential matrices, the image-only fallback, the merge;
* :mod:`.backbone` -- :class:`OfflineGeometryBackbone` (``infer``; its settings:
  :class:`cerpe.backbones.config.OfflineConfig`).
"""
from .backbone import OfflineGeometryBackbone
from .context import OfflineBackboneError, Pass, Recon
from .matching import (PairMatcher, keypoint_depths, match_mnn, pixels_to_rays, reprojection_error, splat_depth,
                       triangulate, triangulation_angle_deg)
from .two_view import merge_image_only

__all__ = ["OfflineGeometryBackbone", "OfflineBackboneError", "Pass", "Recon", "PairMatcher", "keypoint_depths",
           "match_mnn", "pixels_to_rays", "reprojection_error", "splat_depth", "triangulate",
           "triangulation_angle_deg", "merge_image_only"]

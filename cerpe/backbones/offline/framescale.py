"""A running per-frame depth scale for depth priors whose metric scale wanders from frame to frame.

A monocular metric-depth network's map of a frame is off by a scale factor of its own
(several per cent, independent from frame to frame). Every metric result of a pass takes the
scale of the prior it was placed on. That holds for the current view's translation (P3P on
the reference view's points) and for a collaborator's direct estimate (P3P on the robot's
points), whose error along the line between the cameras is then about that factor.

This module keeps a log depth scale of each frame relative to the robot's recent frames,
per robot and through the memos alone (a backbone keeps no state). It brings every own
view of a pass onto one common scale before the metric reconstruction:

* a memo carries ``log_scale = (a, m)`` of its frame. ``a`` is the frame's prior's log
  scale in the robot's running reference. ``m`` is the running mean of ``a`` over its recent
  frames (an exponential mean, rate :data:`FRAME_SCALE_RATE`) when it was the current view;
* a pass takes ``m_ref`` from its previous frame's memo (else its newest keyframe's) and
  multiplies the prior of each own view ``k`` with a memo by ``exp(m_ref - a_k)``;
* once the current view is placed on the (corrected) reference view ``d``, the median log
  ratio ``r`` of the current prior to ``d``'s prior moved into the current camera is its
  scale relative to ``m_ref``. Its memo gets ``a = m_ref + r``, ``m = m_ref + rate r``. Its
  prior is multiplied by ``exp(-r)`` for the rest of the pass (dense refinement, the
  moving mask, the points collaborators are placed on).

A ratio needs no translation to be measured: rotation alone moves ``d``'s points into the
current camera. With a pure scale error it is exact. P3P on points scaled by ``s_d``
gives the translation scaled by ``s_d``, so ``d``'s moved depths are ``s_d z`` where the
current prior reads ``s_0 z``. The correction applies only when ``frame_scale`` is on and
the current view's depth source reports a scale sigma ``depth_rel_sigma >=
FRAME_SCALE_MIN_REL_SIGMA``. A depth sensor's 0 leaves every pass bit for bit as it was;
the backbone never asks which source made the depth.
"""
from __future__ import annotations

import dataclasses
from typing import Any, Mapping, Sequence

import numpy as np

from ...protocols import View
from ..config import OfflineConfig
from .context import Pass
from .matching import map_index
from .vote import VOTE_BLUR_SIGMA, VOTE_GREY_TOL, bilinear, blurred_greys, grid_points, project_points

LogScale = tuple[float, float]  # (a, m): the frame's log scale and the running mean at the time

# a prior is corrected when its source reports at least this relative scale sigma (a monocular
# network's; a depth sensor's is 0)
FRAME_SCALE_MIN_REL_SIGMA = 0.03
FRAME_SCALE_RATE = 0.1  # rate per frame of the running mean of the log scale
FRAME_SCALE_MAX = 0.35  # a frame's scale is measured on ratios within a factor 1 + FRAME_SCALE_MAX
FRAME_SCALE_MIN_PIXELS = 200  # grid pixels a measurement needs (else r = 0)


def enabled(views: Sequence[View], conf: OfflineConfig) -> bool:
    """Whether this pass corrects per-frame scales: ``frame_scale`` on and the current view's
    prior reports a scale sigma of at least :data:`FRAME_SCALE_MIN_REL_SIGMA`."""
    v0 = views[0]
    r = v0.depth_rel_sigma
    return (conf.frame_scale and v0.depth_m is not None and r is not None
            and np.isfinite(r) and float(r) >= FRAME_SCALE_MIN_REL_SIGMA)


def memo_log_scale(memo: Mapping[str, Any] | None) -> LogScale | None:
    """``(a, m)`` of a memo (None: no memo, or one written without a scale)."""
    if memo is None:
        return None
    ls = memo.get("log_scale")
    if ls is None:
        return None
    a, m = (float(x) for x in ls)
    return (a, m) if np.isfinite(a) and np.isfinite(m) else None


def reference_mean(views: Sequence[View], memos: Sequence[Mapping[str, Any] | None]) -> float:
    """``m_ref``: the running mean of the previous frame's memo, else of the first own view
    with a scale (keyframes come newest first); 0 when no view has one (a robot's first
    frames, or after its memory restarted)."""
    order = [k for k in range(1, len(views)) if views[k].role == "previous"]
    order += [k for k in range(1, len(views)) if k not in order and views[k].role != "collaborator"]
    for k in order:
        ls = memo_log_scale(memos[k]) if k < len(memos) else None
        if ls is not None:
            return ls[1]
    return 0.0


def correct_views(views: list[View], memos: Sequence[Mapping[str, Any] | None], m_ref: float) -> list[View]:
    """The views with each own prior ``k > 0`` whose memo has a scale multiplied by
    ``exp(m_ref - a_k)`` (float32, 0 = unknown stays 0); the others as they are."""
    out = list(views)
    for k in range(1, len(views)):
        v = views[k]
        ls = memo_log_scale(memos[k]) if k < len(memos) else None
        if ls is None or v.depth_m is None or v.role == "collaborator":
            continue
        f = np.float32(np.exp(m_ref - ls[0]))
        if f != 1:
            out[k] = dataclasses.replace(v, depth_m=np.asarray(v.depth_m, np.float32) * f)
    return out


def log_ratio(p: Pass, d: int, T_0_d: np.ndarray) -> tuple[float, int]:
    """``(r, n)``: the median log ratio ``r`` of the current view's prior to view ``d``'s prior
    moved into the current camera by ``T_0_d`` (camera-``d`` points into the current camera).

    It is taken over the ``n`` vote grid pixels of ``d`` (its moving ones left out) that land
    inside the current view with a grey level within ``VOTE_GREY_TOL`` and a ratio within a
    factor ``1 + FRAME_SCALE_MAX``. ``r = 0`` when ``n < FRAME_SCALE_MIN_PIXELS``."""
    D0 = np.asarray(p.views[0].depth_m, np.float64)
    H0, W0 = p.feats[0].image_hw
    grey = blurred_greys(p, (d, 0), VOTE_BLUR_SIGMA)
    vv, uu, ok, X = grid_points(p, d, p.moving(d))
    X0, u0, v0, ins = project_points(p, 0, X, T_0_d)
    meas = D0[map_index(v0[ins], D0.shape[0], H0), map_index(u0[ins], D0.shape[1], W0)]
    g_d = grey[0][vv[ok][ins], uu[ok][ins]].astype(np.float64)
    g_0 = bilinear(grey[1], u0[ins], v0[ins]).astype(np.float64)
    with np.errstate(divide="ignore", invalid="ignore"):
        r = np.log(meas / X0[ins, 2])
    use = (np.abs(g_0 - g_d) <= VOTE_GREY_TOL) & np.isfinite(r) & (np.abs(r) <= np.log1p(FRAME_SCALE_MAX))
    n = int(use.sum())
    if n < FRAME_SCALE_MIN_PIXELS:
        return 0.0, n
    return float(np.median(r[use])), n


def update_current(p: Pass, d: int, T_0_d: np.ndarray) -> None:
    """Measure the current view's scale against the placed reference ``d`` (see the module
    docstring), rescale its prior in ``p`` and keep ``p.log_scale_out`` for its memo."""
    r, n = log_ratio(p, d, T_0_d)
    p.counts["frame-scale-measured" if n >= FRAME_SCALE_MIN_PIXELS else "frame-scale-few-pixels"] += 1
    m = p.scale_ref
    p.log_scale_out = (m + r, m + FRAME_SCALE_RATE * r)
    if r != 0.0:
        v0 = p.views[0]
        p.views[0] = dataclasses.replace(v0, depth_m=np.asarray(v0.depth_m, np.float32) * np.float32(np.exp(-r)))

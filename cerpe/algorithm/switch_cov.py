"""The covariance of the switch's estimate (the paper's back end): the pose graph's noise model, no graph.

A direct estimate gets the calibrated covariance of a direct estimate
(:func:`~cerpe.algorithm.graph_model.direct_cov`: its inliers, its anchor verdict, the depth it was
placed on). A propagated one, ``T(t) = X_j(t)^-1 X_j(a) T(a) X_i(a)^-1 X_i(t)`` from the anchor of step
``a``, carries the anchor's covariance moved to ``t`` plus both odometries' noise over ``a -> t``
(:func:`~cerpe.algorithm.graph_model.odometry_cov`, one increment per robot). All covariances are
right perturbations over ``[rotation, translation]`` (``T_true = T exp(xi)``, camera ``i``'s frame), as
:class:`~cerpe.records.PairRecord.cov`; without metric depth the translation block says "unknown"
(the model's ``UNSCALED_TRANS_SIGMA``). What the pose graph back end reports needs none of this: it
has its own (``PairRecord.cov``).
"""
from __future__ import annotations

from typing import Any

import numpy as np

from ..geometry import se3_adjoint, se3_inverse
from .graph_model import DirectEstimate, direct_cov, graph_model, odometry_cov


def switch_cov(agent: Any, rec: Any) -> np.ndarray | None:
    """``[6,6]`` covariance of ``rec`` (a :class:`~cerpe.records.PairRecord` of ``agent`` at its current
    step, the switch back end); None when the record has no estimate or its anchor is not known."""
    if rec.T_cj_ci is None or rec.source not in ("direct", "propagated"):
        return None
    conf = agent.config
    depth = agent.depth
    model = graph_model(conf.backend.graph, conf.anchors.max_unverified_steps, bool(getattr(depth, "metric", True)))
    rel = getattr(depth, "rel_sigma", None)
    if rec.source == "direct":
        return direct_cov(model, DirectEstimate(rec.step, rec.T_cj_ci, int(rec.direct_inliers), rec.anchor_verdict,
                                                depth_rel_sigma=rel))
    pair = agent.s.pairs.get(rec.other)
    anchor = None if pair is None else pair.carried(rec.step)[0]
    pose = agent.s.poses.get(rec.other)
    if anchor is None or anchor.step != rec.anchor_step or pose is None:
        return None
    verdict = "verified" if anchor is pair.anchor else "unverified"
    P = direct_cov(model, DirectEstimate(anchor.step, anchor.T_cj_ci, int(anchor.inliers), verdict, depth_rel_sigma=rel))
    n = max(int(rec.step) - int(anchor.step), 1)
    inc_i = se3_inverse(anchor.X_i) @ agent.X        # ego odometry since the anchor, in camera i(a)
    inc_j = se3_inverse(anchor.X_j) @ pose[1]        # the peer's
    A = se3_adjoint(se3_inverse(inc_i))              # T(a) exp(xi) B = T(a) B exp(Ad(B^-1) xi)
    C = A @ P @ A.T + odometry_cov(model, inc_i, n, depth_rel_sigma=rel)
    Aj = se3_adjoint(se3_inverse(rec.T_cj_ci))       # exp(-eps_j) T = T exp(-Ad(T^-1) eps_j)
    C = C + Aj @ odometry_cov(model, inc_j, n, depth_rel_sigma=rel) @ Aj.T
    return 0.5 * (C + C.T)

"""The pose graph's configuration and noise models (``cerpe-graph``): no solver here.

:class:`GraphConfig` (the knobs of ``backend.graph``), :class:`GraphModel` (the calibrated noise
model: constants, not knobs; lab studies replay other values), the direct estimate and the
estimate the graph returns. :func:`odometry_cov` and :func:`direct_cov` give the ``[6,6]``
covariances of an odometry increment and of a direct estimate, over ``[rotation, translation]``
of a right perturbation (:mod:`cerpe.geometry`). :mod:`cerpe.algorithm.graph` solves with them.
"""
from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field

import numpy as np

from ..errors import CerpeError
from ..geometry import rotation_angle
from ..knobs import Group, knob
from ..reasons import DEGRADATIONS
from .anchors import SETS_ANCHOR
# the translation sigma of a direct estimate or an odometry increment without metric depth (their unit is
# the pass's own): no information next to the unit-length translations of such passes
UNSCALED_TRANS_SIGMA = 100.0
# verdicts that confirm a direct estimate: those that set an anchor and "" (no verdict given); any other
# (unverified, rejected, weak, or a verdict added later) does not
CONFIRMED: frozenset[str] = SETS_ANCHOR | {""}
# the degradations the graph counts (described in cerpe.reasons.DEGRADATIONS)
GRAPH_DEGRADATIONS: tuple[str, ...] = tuple(k for k in DEGRADATIONS if k.startswith("graph:"))


class GraphError(CerpeError, ValueError):
    """A bad graph configuration (names the field)."""


@dataclass(frozen=True)
class GraphConfig(Group):
    """The pose graph's knobs (``backend.graph``); its noise model is :data:`GRAPH_MODEL`."""

    window_nodes: int = knob(20, "direct estimates the incremental smoother keeps; older ones are marginalised",
                             low=2)
    kernel_k: float = knob(2.0, "width of the Cauchy kernel on direct estimates (standard deviations of the "
                           "whitened error)", low=0.0, low_open=True)


@dataclass(frozen=True)
class GraphModel:
    """The pair graph's calibrated noise model, Cauchy kernel and window (:data:`GRAPH_MODEL`).

    Odometry: one increment of ``n`` steps, ``d`` metres and ``a`` radians gets standard
    deviations ``sqrt(n s0^2 + (s_m d)^2 / n + (s_rad a)^2 / n)`` per axis (rotation:
    ``odo_rot_per_step``, ``odo_rot_per_m``, ``odo_rot_per_rad``; translation likewise). Each step
    whose own odometry failed (``X`` kept for want of an estimate) adds ``odo_lost_*``. An
    increment turning more than ``odo_jump_rad`` per step (0: never) is an odometry failure, not a
    motion. Its standard deviations grow by its own angle and distance (plus ``odo_lost_trans``),
    so the graph lets the offset jump with it and the next direct estimates re-anchor it.

    An increment is a failed step too (``odo_lost_*``) when its length differs from the one the
    previous speed predicts by more than ``odo_max_accel_mps2`` times its duration squared, plus
    ``odo_accel_noise_sigmas`` per-step translation sigmas (0: never; needs the steps' stamps).
    This catches an odometry that reports one step much too short (e.g. confused by a co-moving
    vehicle) while its rotation error stays far under ``odo_jump_rad``.

    On a *sensor-like* depth source (the ego's reports ``r <= sensor_max_rel``: a depth sensor, a
    dataset's depth; :func:`sensor_like`) the noise part (not the failure terms) is scaled by
    ``odo_sensor_scale``. Odometry on sensor depth is much more accurate than on a monocular
    prior, so one model for both would be too loose on a sensor (the odometry table of
    ``lab/graph_calibrate.py`` measures the ratio).

    Direct estimates: rotation ``direct_rot_rad``; translation ``direct_trans_m +
    direct_trans_rel |t|`` across the line between the cameras (``|t|`` their distance) and
    ``direct_along_factor`` times that along it. Metric depth errors move the other camera
    mostly along the line of sight. The metric depth the estimate stands on adds its own part,
    each term added in quadrature. With ``r`` its relative scale sigma
    (:attr:`DirectEstimate.depth_rel_sigma`, reported by the depth source;
    ``direct_depth_rel_unknown`` when it reports none), it adds ``direct_depth_rot r`` to the
    rotation, ``direct_depth_across r |t|`` across and ``g r |t|`` along the line. So a monocular
    prior (5-10 %) and a depth sensor (< 1 %) get their own sigmas from one model. The along gain
    ``g`` is per depth kind (:func:`along_gain`): ``direct_depth_along`` when the source reports
    ``r`` (sensor 0, dataset 0.01, monocular prior), ``direct_depth_along_unknown`` when it
    reports none (no metric depth: the distance is the backbone's own scale).

    With ``direct_inliers_ref > 0``, an estimate placed on sensor-like depth (``r <=
    sensor_max_rel``) has all its standard deviations scaled by ``sqrt(direct_inliers_ref /
    inliers)``, clipped to ``[1/direct_inliers_clip, direct_inliers_clip]``. On such depth the
    registration is the error, and it falls with its support. On a monocular prior the depth's
    own distortion dominates, and inliers hardly rank the estimates. Estimates that anchor
    verification left unverified or rejected are scaled by ``unverified_scale`` /
    ``rejected_scale`` (1: only the kernel judges them). ``kernel_k``: the kernel's width in
    standard deviations of the whitened error.

    Until anchor verification has confirmed one of its direct estimates (verdict in
    :data:`CONFIRMED`), the graph reports nothing more than ``max_unverified_steps`` steps after
    its newest direct estimate, as the switch does with an unverified candidate (the same default).

    Uninformative: a propagated estimate whose predicted rotation sigma (``sqrt`` of the rotation
    block's trace) exceeds ``max_sigma_rot_rad`` (0: never) is not reported (``uninformative``; its
    covariance still is). After an odometry failure the walk's covariance says the pose may be
    anywhere. Such a pose is a guess, which the switch does not report either (it drops its anchor
    at an odometry jump). A direct estimate that became a node is always reported.

    Consensus: a robust kernel started at the old estimate keeps it (a non-convex cost has its
    minimum where it starts). So when a new direct estimate fails the chi-square gate
    ``consensus_gate_chi2`` (6 dof) against the graph's estimate, the window's direct estimates
    vote. Those agreeing with both do not vote. If ``consensus_ratio`` times as many agree with the
    new one as with the graph's estimate (and at least ``consensus_min_support``; 0 disables it),
    the window is solved afresh from the new one.

    Silent odometry drift: an odometry that under-reports the motion without flagging it moves the
    true offset between the odometry frames step after step. The innovations of the confirmed
    direct estimates (translation of the measured offset against the graph's before the update, in
    the ego's odometry frame) then grow one way. Estimates sharing a correlated error instead stay a
    constant distance off. The rule fires when ``drift_after`` innovations in a row (0: never;
    unconfirmed ones neither count nor break the run) each point within ``drift_cos`` (cosine) of
    the one before and are longer than it. The newest one's chi-square (6 dof, its covariance plus
    the graph's marginal and walk) must also exceed ``drift_chi2``. Then the walk into each of them
    gets ``drift_inflate`` times the growth of its innovation as translation sigma, and the window
    is solved afresh from the newest one. The next confirmed estimate off the same way (cosine,
    chi-square) is followed at once.

    Without metric depth (``metric`` False: a depth source that never has any) every pass has a unit
    of its own, so neither the direct estimates' translations nor the odometry's share a scale.
    Their translation blocks get :data:`UNSCALED_TRANS_SIGMA` (no information) and the graph fuses
    rotations only. The agent reports the switch's translation direction with the graph's rotation.
    """

    # odometry noise model: calibrated on development data only (lab/graph_calibrate.py)
    odo_rot_per_step: float = 0.0035
    odo_rot_per_m: float = 0.0
    odo_rot_per_rad: float = 0.0244
    odo_trans_per_step: float = 0.026
    odo_trans_per_m: float = 0.17
    odo_lost_rot: float = 0.05
    odo_lost_trans: float = 0.15
    odo_jump_rad: float = 1.0
    odo_sensor_scale: float = 0.4  # the ratio of the two kinds' observed/modelled RMS (see above)
    # about 1 g (m/s^2): no wheeled robot speeds up or brakes faster (tyre friction). A margin of
    # odometry noise sigmas on top keeps a high-rate odometry's jitter from reading as acceleration.
    odo_max_accel_mps2: float = 10.0
    odo_accel_noise_sigmas: float = 2.0
    # direct estimates: the floors (what a depth sensor's estimates get) and the gains on the depth
    # source's rel_sigma per depth kind, calibrated on development data (lab/graph_calibrate.py).
    # direct_rot_rad goes with kernel_k: a rotation sigma far under the estimates' real errors makes
    # every estimate an outlier to every other, and the Cauchy kernel then keeps whichever it started
    # from. These two let the estimates pull on each other (lab/graph_replay.py replays other values).
    direct_rot_rad: float = 0.006
    direct_trans_m: float = 0.001
    direct_trans_rel: float = 0.0275
    direct_along_factor: float = 2.0
    direct_depth_rot: float = 0.05
    direct_depth_across: float = 0.0
    direct_depth_along: float = 0.1
    direct_depth_along_unknown: float = 1.5
    direct_depth_rel_unknown: float = 0.3
    # inlier weighting (sensor-like depth only): ref about a typical direct estimate's inlier count on
    # sensor depth, so a typical estimate keeps the floors
    direct_inliers_ref: float = 100.0
    direct_inliers_clip: float = 3.0
    # depth kinds with r at most this are sensor-like (sensor 0, dataset 0.01; mono-sim 0.094, none: unknown)
    sensor_max_rel: float = 0.05
    unverified_scale: float = 1.0
    rejected_scale: float = 1.0
    kernel_k: float = 2.0
    window_nodes: int = 20
    consensus_min_support: int = 2
    consensus_gate_chi2: float = 22.46
    consensus_ratio: float = 1.5
    # silent odometry drift: set on development runs (lab/graph_replay.py replays other values)
    drift_after: int = 3
    drift_cos: float = 0.8
    drift_chi2: float = 12.59
    drift_inflate: float = 2.0
    max_unverified_steps: int = 2
    max_sigma_rot_rad: float = 0.5
    metric: bool = True
    max_iterations: int = 100
    converge_tol: float = 1e-6
    relinearize_threshold: float = 1e-3
    min_sigma: float = 1e-6

    def __post_init__(self) -> None:
        for name in ("odo_rot_per_step", "odo_rot_per_m", "odo_rot_per_rad", "odo_trans_per_step",
                     "odo_trans_per_m", "odo_lost_rot", "odo_lost_trans", "odo_jump_rad", "odo_max_accel_mps2",
                     "odo_accel_noise_sigmas",
                     "direct_rot_rad", "direct_trans_m",
                     "direct_trans_rel", "direct_inliers_ref", "sensor_max_rel", "min_sigma",
                     "max_sigma_rot_rad", "direct_depth_rot",
                     "direct_depth_across", "direct_depth_along", "direct_depth_along_unknown",
                     "direct_depth_rel_unknown"):
            v = getattr(self, name)
            if not (np.isfinite(v) and v >= 0):
                raise GraphError(f"graph config: {name} must be finite and >= 0, got {v}")
        for name in ("odo_sensor_scale", "direct_inliers_clip", "direct_along_factor", "unverified_scale",
                     "rejected_scale", "kernel_k",
                     "converge_tol", "consensus_gate_chi2", "consensus_ratio", "drift_chi2", "drift_inflate",
                     "relinearize_threshold"):
            v = getattr(self, name)
            if not (np.isfinite(v) and v > 0):
                raise GraphError(f"graph config: {name} must be finite and > 0, got {v}")
        if not (np.isfinite(self.drift_cos) and -1.0 <= self.drift_cos < 1.0):
            raise GraphError(f"graph config: drift_cos must be finite in [-1, 1), got {self.drift_cos}")
        for name, low in (("window_nodes", 2), ("max_iterations", 1), ("consensus_min_support", 0),
                          ("drift_after", 0), ("max_unverified_steps", 0)):
            v = getattr(self, name)
            if int(v) != v or v < low:
                raise GraphError(f"graph config: {name} must be an integer >= {low}, got {v}")


GRAPH_MODEL = GraphModel()


def graph_model(conf: GraphConfig, max_unverified_steps: int, metric: bool = True) -> GraphModel:
    """:data:`GRAPH_MODEL` with the knobs of ``backend.graph``, the anchors' ``max_unverified_steps`` and
    whether the depth source has metric depth at all (``metric``)."""
    return dataclasses.replace(GRAPH_MODEL, window_nodes=int(conf.window_nodes), kernel_k=float(conf.kernel_k),
                               max_unverified_steps=int(max_unverified_steps), metric=bool(metric))


@dataclass(frozen=True)
class DirectEstimate:
    """One direct estimate ``T_cj_ci`` of a step, with what its noise model may use.

    ``inliers``: the registration's inlier count (-1 unknown); ``verdict``: anchor
    verification's (``accepted``, ``verified``, ``unverified``, ``rejected``, ...);
    ``cov``: its own ``[6,6]`` covariance when it has one (None: :func:`direct_cov`);
    ``depth_rel_sigma``: the relative sigma of the scale of the metric depth it was placed on
    (the depth source's ``rel_sigma``, :class:`~cerpe.protocols.MetricDepthSource`; None: unknown).
    """

    step: int
    T_cj_ci: np.ndarray
    inliers: int = -1
    verdict: str = ""
    cov: np.ndarray | None = None
    depth_rel_sigma: float | None = None


@dataclass
class GraphEstimate:
    """What the graph says at one step: ``T_cj_ci`` and its ``[6,6]`` covariance (None before the first node,
    and once an unconfirmed graph expired: ``expired``), the step of its newest node, whether this step's
    direct estimate became one, and the degradations of this step (names of :data:`GRAPH_DEGRADATIONS`).
    ``uninformative``: ``T_cj_ci`` withheld, its predicted rotation sigma above ``max_sigma_rot_rad``."""

    T_cj_ci: np.ndarray | None = None
    cov: np.ndarray | None = None
    node_step: int = -1
    measured: bool = False
    degradations: list[str] = field(default_factory=list)
    expired: bool = False
    uninformative: bool = False


def _diag(rot_sigma: float, trans_sigma: float) -> np.ndarray:
    return np.diag([rot_sigma**2] * 3 + [trans_sigma**2] * 3)


def _known(rel: float | None) -> bool:  # a depth source's reported scale sigma (not None, finite, >= 0)
    return rel is not None and bool(np.isfinite(rel)) and rel >= 0


def _rel(conf: GraphModel, rel: float | None) -> float:
    """A depth source's relative scale sigma, ``direct_depth_rel_unknown`` when it gave none."""
    return float(rel) if _known(rel) else conf.direct_depth_rel_unknown


def along_gain(conf: GraphModel, rel: float | None) -> float:
    """The along-line gain on the depth scale sigma of an estimate whose depth source reported ``rel``
    (None, NaN or negative: none): ``direct_depth_along``, else ``direct_depth_along_unknown``."""
    return conf.direct_depth_along if _known(rel) else conf.direct_depth_along_unknown


def sensor_like(conf: GraphModel, rel: float | None) -> bool:
    """Whether depth that reported ``rel`` is a sensor's or a dataset's (``r <= sensor_max_rel``); a source
    that reported none is not (whatever ``direct_depth_rel_unknown`` says)."""
    return _known(rel) and float(rel) <= conf.sensor_max_rel


def odometry_noise_var(conf: GraphModel, n_steps, dist_m, angle_rad, sensor: bool = False):
    """Per-axis ``(rotation, translation)`` variances of the noise part of an odometry increment of
    ``n_steps`` steps, ``dist_m`` metres and ``angle_rad`` radians (scalars or arrays; the failure
    terms are :func:`odometry_cov`'s); ``sensor``: on sensor-like depth, times ``odo_sensor_scale``^2."""
    n = np.maximum(n_steps, 1)
    var_r = n * conf.odo_rot_per_step**2 + ((conf.odo_rot_per_m * dist_m) ** 2
                                            + (conf.odo_rot_per_rad * angle_rad) ** 2) / n
    var_t = n * conf.odo_trans_per_step**2 + (conf.odo_trans_per_m * dist_m) ** 2 / n
    f = conf.odo_sensor_scale**2 if sensor else 1.0
    return var_r * f, var_t * f


def odometry_cov(conf: GraphModel, T_prev_cur: np.ndarray, n_steps: int, lost_steps: int = 0,
                 speed_change_mps2: float = 0.0, depth_rel_sigma: float | None = None) -> np.ndarray:
    """``[6,6]`` covariance of one odometry increment ``T_prev_cur`` spanning ``n_steps`` steps;
    ``speed_change_mps2``: the acceleration it implies beyond odometry noise (0: none or unknown);
    ``depth_rel_sigma``: the ego's depth source's (:func:`sensor_like`: noise times ``odo_sensor_scale``)."""
    n = max(int(n_steps), 1)
    d = float(np.linalg.norm(T_prev_cur[:3, 3]))
    if conf.odo_max_accel_mps2 > 0 and speed_change_mps2 > conf.odo_max_accel_mps2:
        lost_steps += 1  # no robot accelerates so: the odometry failed without saying so
    a = float(rotation_angle(T_prev_cur[:3, :3]))
    var_r, var_t = odometry_noise_var(conf, n, d, a, sensor_like(conf, depth_rel_sigma))
    var_r += lost_steps * conf.odo_lost_rot**2
    var_t += lost_steps * conf.odo_lost_trans**2
    if conf.odo_jump_rad > 0 and a > conf.odo_jump_rad * n:  # not a motion, a failure: the walk may jump by it
        var_r += a**2
        var_t += (d + conf.odo_lost_trans) ** 2
    if not conf.metric:  # translations in the units of their passes: no information
        var_t = UNSCALED_TRANS_SIGMA**2
    return np.diag([var_r] * 3 + [var_t] * 3)


def direct_cov(conf: GraphModel, est: DirectEstimate) -> np.ndarray:
    """``[6,6]`` covariance of a direct estimate from the calibrated model (see :class:`GraphModel`)."""
    f = 1.0
    if conf.direct_inliers_ref > 0 and est.inliers > 0 and sensor_like(conf, est.depth_rel_sigma):
        c = conf.direct_inliers_clip
        f = float(np.clip(np.sqrt(conf.direct_inliers_ref / est.inliers), 1.0 / c, c))
    if est.verdict == "unverified":
        f *= conf.unverified_scale
    elif est.verdict == "rejected":
        f *= conf.rejected_scale
    T = np.asarray(est.T_cj_ci, dtype=np.float64)
    dist = float(np.linalg.norm(T[:3, 3]))
    r = _rel(conf, est.depth_rel_sigma)
    across = conf.direct_trans_m + dist * np.hypot(conf.direct_trans_rel, conf.direct_depth_across * r)
    along = np.hypot(conf.direct_along_factor * (conf.direct_trans_m + conf.direct_trans_rel * dist),
                     along_gain(conf, est.depth_rel_sigma) * r * dist)
    cov = _diag(f * float(np.hypot(conf.direct_rot_rad, conf.direct_depth_rot * r)), f * across)
    if dist > 0 and along != across:
        w = T[:3, :3].T @ T[:3, 3] / dist  # the line between the cameras, in camera i (the perturbation's frame)
        cov[3:, 3:] += f**2 * (along**2 - across**2) * np.outer(w, w)
    if not conf.metric:  # translations in the units of their passes: no information
        cov[3:, :] = 0.0
        cov[:, 3:] = 0.0
        cov[3:, 3:] = np.eye(3) * UNSCALED_TRANS_SIGMA**2
    return cov


def usable_cov(cov: np.ndarray | None) -> bool:
    """A ``[6,6]`` finite, symmetric, positive definite covariance."""
    if cov is None:
        return False
    C = np.asarray(cov, dtype=np.float64)
    if C.shape != (6, 6) or not np.isfinite(C).all():
        return False
    if np.abs(C - C.T).max() > 1e-9 * max(np.abs(C).max(), 1e-300):
        return False
    try:
        np.linalg.cholesky(C)
    except np.linalg.LinAlgError:
        return False
    return True

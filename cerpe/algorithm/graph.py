"""A robust pose graph per ordered pair of robots: the back end of ``cerpe-graph``.

Not in the paper. CERPE *switches*: a direct estimate when the gate opens, else the
last anchor propagated with both odometries; every earlier anchor is forgotten and a
wrong one is carried until the next. This back end keeps every direct estimate of the
pair (accepted or rejected by anchor verification) and both robots' odometry in one
pose graph under a robust kernel, so a wrong estimate is down-weighted, not followed.

Formulation. Robot i's odometry poses ``X_i`` live in its own frame ``o_i``, robot j's
broadcast poses ``X_j`` in ``o_j``; the unknown offset ``O = T_oj_oi`` relates them:
``T_cj_ci(t) = X_j(t)^-1 O X_i(t)``. With exact odometry ``O`` is constant. An odometry
error ``eps`` (body frame of the new camera) of one increment moves it by a right
perturbation ``Ad(O^-1 X_j) eps_j - Ad(X_i) eps_i``, so ``O`` is a random walk whose
steps both odometries' noise models give (:func:`odometry_cov`). The graph has one
variable ``O_k`` per step with a direct estimate (a *node*). Between consecutive nodes sits a
``BetweenFactorPose3`` (identity, the walk accumulated since). On each node sits a
``PriorFactorPose3`` at ``O_meas = X_j z X_i^-1`` from the direct estimate ``z``, with its
noise model (:func:`direct_cov`) under a Cauchy kernel. Between nodes nothing is
solved: the estimate at step t is the newest node's estimate moved by both odometries, its
covariance the node's marginal plus the walk since (a filter's prediction). Poses are
re-centred on the first node's ``X_i``, ``X_j`` so lever arms are distances travelled.

Solved incrementally with GTSAM's ``IncrementalFixedLagSmoother`` (iSAM2 over the last ``window_nodes``
nodes, older ones marginalised): an update costs the same after an hour as after a minute. Covariances
are ``[6,6]`` over ``[rotation, translation]`` of a right perturbation (:mod:`cerpe.geometry`).

Bad input never raises out of :meth:`PairGraph.step`. A degenerate covariance, a direct estimate whose
poses the graph does not have (out of order), or a solver that throws or does not converge come back
as degradation names (:data:`GRAPH_DEGRADATIONS`), and the last good estimate is kept.
"""
from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np

from ..geometry import se3_adjoint
from .graph_model import (  # noqa: F401 -- the config, estimates and noise models, re-exported
    CONFIRMED, GRAPH_DEGRADATIONS, GRAPH_MODEL, DirectEstimate, GraphConfig, GraphError, GraphEstimate, GraphModel,
    along_gain, direct_cov, graph_model, odometry_cov, usable_cov,
)

log = logging.getLogger(__name__)


def _inv(T: np.ndarray) -> np.ndarray:
    """Inverse of a rigid transform (inputs here are checked poses: no validation, it runs every step)."""
    out = np.eye(4)
    out[:3, :3], out[:3, 3] = T[:3, :3].T, -T[:3, :3].T @ T[:3, 3]
    return out


def _sym(C: np.ndarray) -> np.ndarray:
    return 0.5 * (C + C.T)


def _log(T: np.ndarray) -> np.ndarray:
    """``[rotation vector, translation]`` of a rigid transform (first order in the translation: a gate, not a solver)."""
    R = T[:3, :3]
    c = np.clip((np.trace(R) - 1.0) / 2.0, -1.0, 1.0)
    a = float(np.arccos(c))
    w = np.array([R[2, 1] - R[1, 2], R[0, 2] - R[2, 0], R[1, 0] - R[0, 1]])
    if a < 1e-9:
        return np.concatenate([0.5 * w, T[:3, 3]])
    if np.pi - a < 1e-6:  # a half turn: the axis from the symmetric part
        axis = np.sqrt(np.clip((np.diag(R) + 1.0) / 2.0, 0.0, None))
        k = int(np.argmax(axis))
        axis = (R[:, k] + np.eye(3)[k]) / np.linalg.norm(R[:, k] + np.eye(3)[k])
        return np.concatenate([a * axis, T[:3, 3]])
    return np.concatenate([a / (2.0 * np.sin(a)) * w, T[:3, 3]])


def _log_batch(T: np.ndarray) -> np.ndarray:
    """:func:`_log` of ``[n,4,4]`` transforms, ``[n,6]``."""
    R = T[:, :3, :3]
    c = np.clip((np.trace(R, axis1=1, axis2=2) - 1.0) / 2.0, -1.0, 1.0)
    a = np.arccos(c)
    w = np.stack([R[:, 2, 1] - R[:, 1, 2], R[:, 0, 2] - R[:, 2, 0], R[:, 1, 0] - R[:, 0, 1]], axis=1)
    f = np.where(a < 1e-9, 0.5, a / (2.0 * np.sin(np.where(a < 1e-9, 1.0, a))))
    out = np.concatenate([f[:, None] * w, T[:, :3, 3]], axis=1)
    for k in np.flatnonzero(np.pi - a < 1e-6):  # half turns: the axis from the symmetric part
        out[k] = _log(T[k])
    return out


@dataclass
class _Node:
    """A node of the window (consensus check, rebuild): key, measured offset, its covariance, walk since the last."""

    key: int
    O_meas: np.ndarray
    cov: np.ndarray
    walk: np.ndarray


class _Solver:
    """GTSAM's incremental fixed-lag smoother over the offset nodes (keys = node numbers)."""

    def __init__(self, conf: GraphModel) -> None:
        import gtsam

        self.gtsam, self.conf = gtsam, conf
        params = gtsam.ISAM2Params()
        params.setRelinearizeThreshold(conf.relinearize_threshold)
        params.relinearizeSkip = 1
        self.smoother = gtsam.IncrementalFixedLagSmoother(float(conf.window_nodes), params)

    def _robust(self, cov: np.ndarray):
        g = self.gtsam
        base = g.noiseModel.Gaussian.Covariance(cov)
        return g.noiseModel.Robust.Create(g.noiseModel.mEstimator.Cauchy.Create(self.conf.kernel_k), base)

    def add(self, key: int, init: np.ndarray, prior: tuple[np.ndarray, np.ndarray] | None, robust_prior: bool,
            between: tuple[int, np.ndarray] | None) -> tuple[np.ndarray, np.ndarray, bool]:
        """Add node ``key`` (initial value ``init``) with an optional prior ``(O, cov)`` and an optional
        between factor ``(previous key, cov)``; returns ``(estimate, marginal covariance, converged)``."""
        g = self.gtsam
        graph, values, stamps = g.NonlinearFactorGraph(), g.Values(), g.FixedLagSmootherKeyTimestampMap()
        if between is not None:
            graph.add(g.BetweenFactorPose3(between[0], key, g.Pose3(), g.noiseModel.Gaussian.Covariance(between[1])))
        if prior is not None:
            noise = self._robust(prior[1]) if robust_prior else g.noiseModel.Gaussian.Covariance(prior[1])
            graph.add(g.PriorFactorPose3(key, g.Pose3(prior[0]), noise))
        values.insert(key, g.Pose3(init))
        stamps.insert((key, float(key)))
        return self._settle(graph, values, stamps, key)

    def rebuild(self, nodes: list["_Node"], init: np.ndarray) -> tuple[np.ndarray, np.ndarray, bool]:
        """A fresh smoother over ``nodes`` (oldest first: robust priors, walks between them), every
        node started at ``init``; returns the newest node's ``(estimate, marginal covariance, converged)``."""
        g = self.gtsam
        graph, values, stamps = g.NonlinearFactorGraph(), g.Values(), g.FixedLagSmootherKeyTimestampMap()
        prev = None
        for n in nodes:
            if prev is not None:
                graph.add(g.BetweenFactorPose3(prev, n.key, g.Pose3(), g.noiseModel.Gaussian.Covariance(n.walk)))
            graph.add(g.PriorFactorPose3(n.key, g.Pose3(n.O_meas), self._robust(n.cov)))
            values.insert(n.key, g.Pose3(init))
            stamps.insert((n.key, float(n.key)))
            prev = n.key
        return self._settle(graph, values, stamps, nodes[-1].key)

    def _settle(self, graph, values, stamps, key: int) -> tuple[np.ndarray, np.ndarray, bool]:
        g = self.gtsam
        self.smoother.update(graph, values, stamps)
        est = self.smoother.calculateEstimatePose3(key)
        converged = False
        for _ in range(self.conf.max_iterations):
            self.smoother.update(g.NonlinearFactorGraph(), g.Values(), g.FixedLagSmootherKeyTimestampMap())
            new = self.smoother.calculateEstimatePose3(key)
            change = float(np.linalg.norm(g.Pose3.Logmap(est.between(new))))
            est = new
            if change <= self.conf.converge_tol:
                converged = True
                break
        return est.matrix(), np.asarray(self.smoother.marginalCovariance(key)), converged


class PairGraph:
    """The pose graph of one ordered pair (ego i about robot j), fed once per step by :meth:`step`.

    ``depth_rel_sigma``: the ego's depth source's relative scale sigma (None: none reported); it sets
    the noise model of both odometries (:func:`odometry_cov`): the messages do not say the other
    robot's depth kind, and a team is taken to share one.
    """

    def __init__(self, conf: GraphModel | None = None, depth_rel_sigma: float | None = None) -> None:
        self.conf = conf or GRAPH_MODEL
        self.depth_rel_sigma = depth_rel_sigma  # the ego's depth source's: both odometries' noise model
        self._ref: tuple[np.ndarray, np.ndarray] | None = None  # X_i, X_j at the first node
        self._last_i: tuple[int, np.ndarray] | None = None
        self._last_j: tuple[int, np.ndarray] | None = None
        self._lost = 0  # steps of failed own odometry not yet in the walk
        self._stamps: dict[int, float] = {}  # step -> stamp (s) of the ego's recent steps (both robots' clock)
        self._speed: dict[int, float] = {}  # last increment's speed (m/s): 0 ego, 1 other
        self._Q = np.zeros((6, 6))  # random walk of O since the newest node, in O's tangent there
        self._key = -1
        self._node_step = -1
        self._O: np.ndarray | None = None  # newest node's estimate (re-centred frames)
        self._P: np.ndarray | None = None  # its marginal covariance
        self._solver: _Solver | None = None
        self._nodes: list[_Node] = []  # the window's nodes (consensus check, rebuild)
        self.n_nodes = 0
        self.n_reseeds = 0  # windows solved afresh from a new direct estimate (consensus)
        self.confirmed = False  # a node's direct estimate was confirmed by anchor verification
        self.n_drifts = 0  # windows re-solved to follow a silent odometry drift
        self._innov: list[tuple[int, np.ndarray]] = []  # (node key, translation innovation): the run growing one way
        self._drifting: np.ndarray | None = None  # unit direction of the drift being followed (None: none)
        self._direct_step = -1  # the newest step with a direct estimate (a node or not)

    # ------------------------------------------------------------------ frames
    def _local(self, X: np.ndarray, which: int) -> np.ndarray:
        return _inv(self._ref[which]) @ X

    # ------------------------------------------------------------------ odometry
    def _speed_change(self, which: int, inc: np.ndarray, s0: int, s1: int) -> float:
        """The acceleration (m/s^2) increment ``inc`` (steps ``s0 -> s1``) implies beyond odometry noise:
        its length against the robot's previous speed kept, less ``odo_accel_noise_sigmas`` times the
        per-step translation sigma, over its duration squared. 0 where a stamp is missing (then the
        next increment is not judged either). Keeps the new speed."""
        t0, t1 = self._stamps.get(s0), self._stamps.get(s1)
        if t0 is None or t1 is None or not t1 > t0:
            self._speed.pop(which, None)  # the next increment has no speed to be judged against
            return 0.0
        dt, d = t1 - t0, float(np.linalg.norm(inc[:3, 3]))
        prev, self._speed[which] = self._speed.get(which), d / dt
        if prev is None:
            return 0.0
        miss = abs(d - prev * dt) - self.conf.odo_accel_noise_sigmas * self.conf.odo_trans_per_step
        return max(miss, 0.0) / dt**2

    def _walk_i(self, step: int, X_i: np.ndarray, own_ok: bool) -> None:
        if not own_ok:
            self._lost += 1
        last, self._last_i = self._last_i, (int(step), np.array(X_i, dtype=np.float64))
        if self._O is None or last is None or step <= last[0]:
            self._lost = 0 if self._O is None else self._lost
            return
        inc = _inv(last[1]) @ X_i
        S = odometry_cov(self.conf, inc, step - last[0], self._lost, self._speed_change(0, inc, last[0], step),
                         self.depth_rel_sigma)
        self._lost = 0
        A = se3_adjoint(self._local(X_i, 0))
        self._Q = _sym(self._Q + A @ S @ A.T)

    def _walk_j(self, step: int, X_j: np.ndarray) -> None:
        last = self._last_j
        if last is not None and step <= last[0]:
            return
        self._last_j = (int(step), np.array(X_j, dtype=np.float64))
        if self._O is None or last is None:
            return
        inc = _inv(last[1]) @ X_j
        S = odometry_cov(self.conf, inc, step - last[0], 0, self._speed_change(1, inc, last[0], step),
                         self.depth_rel_sigma)
        A = se3_adjoint(_inv(self._O) @ self._local(X_j, 1))
        self._Q = _sym(self._Q + A @ S @ A.T)

    # ------------------------------------------------------------------ nodes
    def _floor(self, C: np.ndarray) -> np.ndarray:
        return _sym(C) + np.eye(6) * self.conf.min_sigma**2

    def _restart(self) -> None:
        """A fresh smoother holding only the last good node (Gaussian prior at its estimate and marginal)."""
        self._solver = None
        self._nodes = []
        self._innov, self._drifting = [], None  # innovations were against the window it drops
        if self._O is None:
            return
        try:
            solver = _Solver(self.conf)
            solver.add(self._key + 1, self._O, (self._O, self._floor(self._P)), False, None)
        except Exception as exc:  # noqa: BLE001 -- GTSAM raises plain RuntimeErrors; keep the estimate anyway
            log.debug("graph restart failed: %s", exc)
            return
        self._solver, self._key = solver, self._key + 1

    def _measure(self, step: int, direct: DirectEstimate, out: GraphEstimate) -> None:
        if (direct.step != step or self._last_j is None or self._last_j[0] != step
                or self._last_i is None or self._last_i[0] != step or step <= self._node_step):
            out.degradations.append("graph:out-of-order")
            return
        z = np.asarray(direct.T_cj_ci, dtype=np.float64)
        cov_z = direct_cov(self.conf, direct) if direct.cov is None else np.asarray(direct.cov, dtype=np.float64)
        if z.shape != (4, 4) or not np.all(np.isfinite(z)) or not usable_cov(cov_z):
            out.degradations.append("graph:degenerate-covariance")
            return
        first = self._ref is None
        if first:
            self._ref = (self._last_i[1].copy(), self._last_j[1].copy())
        Xi, Xj = self._local(self._last_i[1], 0), self._local(self._last_j[1], 1)
        O_meas = Xj @ z @ _inv(Xi)
        A = se3_adjoint(Xi)
        cov_O = self._floor(A @ cov_z @ A.T)
        Q = self._floor(self._Q)
        if not (usable_cov(cov_O) and usable_cov(Q)):
            out.degradations.append("graph:degenerate-covariance")
            if first:
                self._ref = None
            return
        if self._solver is None and self._O is not None:
            self._restart()  # after a failure: continue from the last good node
        linked = self._solver is not None and self._O is not None
        innov = None  # (translation innovation, its chi-square) against the graph before this estimate
        if linked and direct.verdict in CONFIRMED and self.conf.drift_after > 0:
            r = _log(_inv(self._O) @ O_meas)
            try:
                innov = (r[3:].copy(), float(r @ np.linalg.solve(cov_O + self._P + Q, r)))
            except np.linalg.LinAlgError:
                innov = None
        try:
            if self._solver is None:
                self._solver = _Solver(self.conf)
            key = self._key + 1
            O, P, converged = self._solver.add(key, O_meas if self._O is None else self._O, (O_meas, cov_O), True,
                                               (self._key, Q) if linked else None)
        except Exception as exc:  # noqa: BLE001 -- GTSAM raises plain RuntimeErrors (indefinite system, ...)
            log.debug("graph update failed at step %d: %s", step, exc)
            out.degradations.append("graph:solver-failed")
            self._recover(first)
            return
        if not converged:
            out.degradations.append("graph:not-converged")
            self._recover(first)
            return
        if not (np.all(np.isfinite(O)) and usable_cov(_sym(P))):
            out.degradations.append("graph:solver-failed")
            self._recover(first)
            return
        self._nodes = (self._nodes + [_Node(key, O_meas, cov_O, Q)])[-self.conf.window_nodes:]
        self.confirmed = self.confirmed or direct.verdict in CONFIRMED
        if linked:
            O, P = self._consensus(O, _sym(P))
            O, P = self._drift(O, _sym(P), innov)
        self._key, self._node_step, self._O, self._P = key, step, O, _sym(P)
        self._Q = np.zeros((6, 6))
        self.n_nodes += 1
        out.measured = True

    def _agree(self, O: np.ndarray) -> np.ndarray:
        """Which of the window's direct estimates (newest first) agree with the offset ``O`` at the newest
        node: chi-square gate on each one's covariance plus the walk from it to the newest node."""
        nodes = self._nodes[::-1]
        M = np.einsum("ij,njk->nik", _inv(O), np.stack([n.O_meas for n in nodes]))
        walks = np.stack([np.zeros((6, 6))] + [n.walk for n in nodes[:-1]]).cumsum(axis=0)
        C = np.stack([n.cov for n in nodes]) + walks
        r = _log_batch(M)
        try:
            d2 = np.einsum("ni,ni->n", r, np.linalg.solve(C, r[..., None])[..., 0])
        except np.linalg.LinAlgError:
            return np.zeros(len(nodes), dtype=bool)
        return d2 <= self.conf.consensus_gate_chi2

    def _consensus(self, O: np.ndarray, P: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The window solved afresh from the newest direct estimate when clearly more estimates agree
        with it than with the graph's estimate ``O`` (which a robust kernel started there would keep).
        Estimates that agree with both (e.g. behind an odometry jump) do not vote."""
        need = self.conf.consensus_min_support
        new = self._nodes[-1]
        if need <= 0 or len(self._nodes) < need:
            return O, P
        r = _log(_inv(O) @ new.O_meas)
        if float(r @ np.linalg.solve(new.cov + P, r)) <= self.conf.consensus_gate_chi2:
            return O, P
        a_new, a_cur = self._agree(new.O_meas), self._agree(O)
        s_new, s_cur = int(np.sum(a_new & ~a_cur)), int(np.sum(a_cur & ~a_new))
        if s_new < need or s_new < self.conf.consensus_ratio * max(s_cur, 1):
            return O, P
        try:
            solver = _Solver(self.conf)
            O2, P2, converged = solver.rebuild(self._nodes, new.O_meas)
        except Exception as exc:  # noqa: BLE001 -- GTSAM raises plain RuntimeErrors; keep the incremental result
            log.debug("graph consensus rebuild failed: %s", exc)
            return O, P
        if not (converged and np.all(np.isfinite(O2)) and usable_cov(_sym(P2))):
            return O, P
        self._solver = solver
        self.n_reseeds += 1
        return O2, _sym(P2)

    def _drift(self, O: np.ndarray, P: np.ndarray, innov: tuple[np.ndarray, float] | None
               ) -> tuple[np.ndarray, np.ndarray]:
        """The window re-solved with its walks opened when the innovations of confirmed direct estimates
        grow one way (a silent odometry drift, see :class:`GraphModel`); else ``(O, P)``. ``innov``:
        the newest estimate's translation innovation and chi-square (None: unconfirmed, leaves the run)."""
        c = self.conf
        if innov is None:
            return O, P
        r, d2 = innov
        nr = float(np.linalg.norm(r))
        key = self._nodes[-1].key
        if self._drifting is not None:  # following a detected drift: off the same way again -> follow at once
            if nr > 0 and float(self._drifting @ r) / nr > c.drift_cos and d2 > c.drift_chi2:
                run = [(key, r)]
            else:
                self._drifting, self._innov = None, [(key, r)]
                return O, P
        else:
            run = self._innov + [(key, r)]
            if len(run) >= 2:
                a = run[-2][1]
                na = float(np.linalg.norm(a))
                if not (na > 0 and nr > na and float(a @ r) / (na * nr) > c.drift_cos):
                    run = [run[-1]]
            self._innov = run
            if len(run) < c.drift_after or d2 <= c.drift_chi2:
                return O, P
        grown, prev = {}, np.zeros(3)
        for k, rk in run:  # each walk into a run's node opened by the growth of the innovation
            grown[k], prev = c.drift_inflate * float(np.linalg.norm(rk - prev)), rk
        nodes = []
        for n in self._nodes:
            if n.key in grown:
                w = n.walk.copy()
                w[3:, 3:] += np.eye(3) * grown[n.key] ** 2
                n = _Node(n.key, n.O_meas, n.cov, w)
            nodes.append(n)
        try:
            solver = _Solver(c)
            O2, P2, converged = solver.rebuild(nodes, nodes[-1].O_meas)
        except Exception as exc:  # noqa: BLE001 -- GTSAM raises plain RuntimeErrors; keep the incremental result
            log.debug("graph drift rebuild failed: %s", exc)
            return O, P
        if not (converged and np.all(np.isfinite(O2)) and usable_cov(_sym(P2))):
            return O, P
        self._solver, self._nodes = solver, nodes
        self._drifting, self._innov = r / max(nr, 1e-12), []
        self.n_drifts += 1
        return O2, _sym(P2)

    def _recover(self, first: bool) -> None:
        if self._O is None:  # nothing good yet: forget the frames too, the next estimate starts afresh
            self._ref, self._solver, self._key = None, None, -1
            return
        self._restart()

    # ------------------------------------------------------------------ the step
    def step(self, step: int, X_i: np.ndarray, X_j: np.ndarray | None = None, X_j_step: int = -1,
             direct: DirectEstimate | None = None, own_ok: bool = True, stamp_s: float | None = None) -> GraphEstimate:
        """Take in this step's poses (and direct estimate), return the graph's estimate.

        Args:
            step: the step index (increasing).
            X_i: ``[4,4]`` ego robot's odometry pose ``T_odom_cam`` at ``step``.
            X_j: the newest pose of the other robot this robot received (None: none yet),
                broadcast at ``X_j_step`` (``< step`` when this step's pose is missing).
            direct: this step's direct estimate of ``T_cj_ci``, if any.
            own_ok: False when the ego robot's odometry failed at this step (``X_i`` kept
                without an estimate): the walk gets ``odo_lost_*`` for it.
            stamp_s: the step's time (s; the team's steps share a clock). With it an increment
                whose speed changes faster than ``odo_max_accel_mps2`` counts as a failed step.

        Returns:
            :class:`GraphEstimate`: None pose before the first node; never raises for bad
            numbers (they come back as degradations).
        """
        out = GraphEstimate()
        if stamp_s is not None and np.isfinite(stamp_s):
            self._stamps[int(step)] = float(stamp_s)
            if len(self._stamps) > 64:  # the last few steps are all an increment can span
                for k in sorted(self._stamps)[:-32]:
                    del self._stamps[k]
        self._walk_i(step, X_i, own_ok)
        if X_j is not None:
            self._walk_j(int(X_j_step), X_j)
        if direct is not None:
            self._direct_step = int(step)
            self._measure(step, direct, out)
        if self._O is None or self._last_j is None:
            return out
        Xi, Xj = self._local(self._last_i[1], 0), self._local(self._last_j[1], 1)
        T = _inv(Xj) @ self._O @ Xi
        out.node_step = self._node_step
        if not self.confirmed and step - self._direct_step > self.conf.max_unverified_steps:
            out.expired = True  # as the switch: an unverified estimate is propagated a few steps only
            return out
        A = se3_adjoint(_inv(Xi))
        out.T_cj_ci, out.cov = T, _sym(A @ (self._P + self._Q) @ A.T)
        lim = self.conf.max_sigma_rot_rad
        if lim > 0 and not out.measured and np.sqrt(max(np.trace(out.cov[:3, :3]), 0.0)) > lim:
            out.T_cj_ci, out.uninformative = None, True  # a pose that may be anywhere: a guess, not reported
        return out

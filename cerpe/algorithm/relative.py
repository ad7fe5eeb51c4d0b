"""Phases 7b and 8 of a robot: peers' poses, shared estimates, and this step's relative pose per peer.

:class:`Relative` is a collaborator of :class:`~cerpe.algorithm.agent.RobotAgent` over the robot's
:class:`~cerpe.algorithm.state.RobotState` (odometry ``X``, anchors, pose logs, graphs). Phase 8
(:meth:`Relative.relative`) is the paper's switch: this step's verified direct estimate, else the
pair's anchor propagated with both odometries; with ``backend="graph"`` the pair's pose graph
(:mod:`~cerpe.algorithm.graph`) answers instead. Phase 7b is our extension (``share_estimates``).
"""
from __future__ import annotations

from typing import Any, Mapping

import numpy as np

from ..geometry import pose_cov_sigmas
from ..messages import EstimateMessage
from ..reasons import join, split
from ..records import PairRecord
from .anchors import NOT_REPORTED, Anchor, PairAnchors
from .bridge import PoseLog
from .direct import REASON_SHARED, SHARED_VIA, direct_estimates, estimate_message, shared_estimate
from .graph import DirectEstimate, PairGraph, graph_model
from .poses import check_pose
from .state import PairInfo, RobotState, StepState, timed

from .config import AlgorithmConfig
from .gating import Gate
from .late import LateRegistrations

# reasons that describe the switch's anchors only (the graph keeps every direct estimate)
_SWITCH_ONLY = frozenset({"no-anchor", "unverified", "unverified-expired", "unverified-held", "direct-rejected",
                          "direct-weak"})


class Relative:
    """Phases 7b (shared estimates) and 8 (relative poses) of one robot over its
    :class:`~cerpe.algorithm.state.RobotState`; ``depth``: its depth source (the graph's noise model
    reads its ``rel_sigma``), ``gate``: its :class:`~cerpe.algorithm.gating.Gate` (was the gate open,
    what did the request bring)."""

    def __init__(self, state: RobotState, config: AlgorithmConfig, depth: Any, gate: Gate,
                 late: LateRegistrations | None = None) -> None:
        self.s, self.config, self.depth, self.gate, self.late = state, config, depth, gate, late

    # ---------------------------------------------------------------- 8. relative poses
    def note_pose(self, other: str, step: int, X_j: np.ndarray) -> None:
        """Remember robot ``other``'s broadcast odometry pose (and advance its odometer)."""
        X = check_pose(X_j, f"{self.s.where()}: pose of robot {other}")
        self.s.poses[other] = (int(step), X)
        self.odometer(other, int(step), X)
        if other != self.s.robot_id:
            self.log_pose(other, int(step), X)

    def reply_missing(self, other: str) -> None:
        """The gate opened for ``other`` but no reply came (request or reply lost): counted; the anchor is carried."""
        self.s.degrade("msg:reply-missing")
        self.s.step_state().gate_reason.setdefault(other, "reply-missing")

    def log_pose(self, other: str, step: int, X: np.ndarray) -> None:
        log_ = self.s.pose_logs.setdefault(other, PoseLog())
        for _ in range(log_.note(step, X)):  # anchors stored with a bridged pose, now interpolated
            self.s.degrade("pose:bridged-next")

    def odometer(self, robot: str, step: int, X: np.ndarray) -> float:
        """Metres ``robot`` travelled: the distances between the successive poses seen of it, summed."""
        last = self.s.odometers.get(robot)
        if last is not None and step <= last[0]:
            return last[2]
        total = 0.0 if last is None else last[2] + float(np.linalg.norm(X[:3, 3] - last[1]))
        self.s.odometers[robot] = (step, X[:3, 3].copy(), total)
        return total

    # ---------------------------------------------------------------- 7b. shared estimates (our extension)
    def estimate_frame(self, index_of: Mapping[str, int]) -> bytes:
        """The ``estimate`` frame of this step (``messages.share_estimates``): the best own direct
        estimate of each peer (wire index ``index_of``) whose image this pass held. Sent even when it
        holds none, so that a peer waiting for it need not wait out its deadline."""
        st = self.s.step_state()
        best = {}
        for other in list(st.collab_index) + [o for o in st.landed if o not in st.collab_index]:
            ests, _ = self._directs(st, other)
            if ests and other in index_of:
                best[int(index_of[other])] = ests[0]
        return estimate_message(self.s.index, st.step, best).encode()

    def note_estimates(self, other: str, msg: EstimateMessage) -> None:
        """Keep robot ``other``'s estimate of this robot from its ``estimate`` frame of this step, unless
        it stands on fewer than ``anchors.min_inliers`` registration inliers.

        Where this robot placed nothing itself, the peer's estimates tend to stand on few inliers
        and to be much less accurate than the robot's own: the bar keeps the weakest out."""
        st = self.s.step_state()
        if int(msg.step) != st.step:
            self.s.degrade("msg:stale-estimate")
            return
        got = shared_estimate(msg, self.s.index)
        bar = int(self.config.anchors.min_inliers)
        if got is not None and not 0 <= got[3] < bar:  # below the bar that replaces an anchor: too weak
            st.shared[other] = got
            self.s.shared_steps[other] = st.step

    def _directs(self, st: StepState, other: str) -> tuple[list, str]:
        """:func:`~cerpe.algorithm.direct.direct_estimates` of ``other``, once per step; with a registrar,
        those of the registration that landed this step, carried to it (:mod:`~cerpe.algorithm.late`)."""
        if other not in st.directs:
            landed = st.landed.get(other)
            if landed is not None and self.late is not None:
                st.directs[other] = self.late.bring_forward(st, other, landed)
            else:
                st.directs[other] = direct_estimates(st, other, self.s.X, self.s.degrade)
        return st.directs[other]

    def relative(self, other: str) -> tuple[str, np.ndarray | None, str, int]:
        """This step's estimate of ``T_cj_ci`` for robot ``other``: ``(source, T or None, reason, anchor_step)``."""
        st = self.s.step_state()
        with timed(st, "propagation"):
            return self._relative(st, other)

    def pair_record(self, other: str, bytes_pair: int = 0) -> PairRecord:
        """This step's :class:`~cerpe.records.PairRecord` about ``other`` (calls :meth:`relative`)."""
        st = self.s.step_state()
        source, T, reason, anchor_step = self.relative(other)
        cov = switch = None
        if self.config.backend.kind == "graph":
            switch = (source, T, reason, anchor_step)
            source, T, reason, anchor_step, cov = self._graph_relative(st, other, switch)
        info = st.pair_info.get(other, PairInfo())
        # what the request policy reads: did the image place, did it set the anchor? (a registration
        # apart from the step: when it lands)
        if other in st.landed or (st.requested.get(other) and other not in st.pending_peers):
            self.gate.note_request(other, info)
        best, via = st.memory_scores.get(other, (float("nan"), -1))
        return PairRecord(step=st.step, stamp_s=st.stamp_s, ego=self.s.robot_id, other=other,
                          gate_score=float(st.scores.get(other, float("nan"))), gate_open=self.gate.gate_open(other),
                          source=source, T_cj_ci=T, reason=reason, bytes_pair=int(bytes_pair),
                          anchor_step=anchor_step, gate_score_memory=float(best), gate_via=int(via),
                          direct_via=info.direct_via, anchor_verdict=info.verdict,
                          check_rot_rad=info.check_rot_rad, check_trans_m=info.check_trans_m, cov=cov,
                          T_direct=info.direct_T, direct_inliers=info.direct_inliers, switch=switch,
                          request_skipped=other in st.skipped)

    def _graph_relative(self, st: StepState, other: str,
                        switch: tuple) -> tuple[str, np.ndarray | None, str, int, np.ndarray | None]:
        """``backend="graph"``: the pair graph's estimate instead of the switch's (:mod:`~cerpe.algorithm.graph`).

        The graph takes this step's odometry poses and this step's direct estimate (the
        one anchor verification judged, whatever its verdict: the robust kernel weighs
        it). ``source`` is ``direct`` when that estimate became a node, ``propagated``
        otherwise, ``none`` before the first node; ``anchor_step`` is the newest node's step.
        ``switch``: the switch's ``(source, T, reason, anchor_step)`` of this step. Without metric
        depth (the depth source's ``metric`` False) the graph fuses rotations only. It reports where
        the switch does, with the switch's translation direction and its own rotation (translation
        covariance unknown: NaN). So it is never worse than the estimates it fuses.
        """
        with timed(st, "graph"):
            return self._graph_step(st, other, switch)

    def _graph_step(self, st: StepState, other: str,
                    switch: tuple) -> tuple[str, np.ndarray | None, str, int, np.ndarray | None]:
        metric = bool(getattr(self.depth, "metric", True))
        info = st.pair_info.get(other, PairInfo())
        graph = self.s.graphs.get(other)
        if graph is None:
            model = graph_model(self.config.backend.graph, self.config.anchors.max_unverified_steps, metric)
            graph = self.s.graphs[other] = PairGraph(model, getattr(self.depth, "rel_sigma", None))
        pose = self.s.poses.get(other)
        direct = (None if info.direct_T is None else
                  DirectEstimate(st.step, info.direct_T, info.direct_inliers, info.verdict,
                                 depth_rel_sigma=getattr(self.depth, "rel_sigma", None)))
        res = graph.step(st.step, self.s.X, None if pose is None else pose[1], -1 if pose is None else pose[0],
                         direct, own_ok=st.ego_status in ("ok", "first", "external"), stamp_s=st.stamp_s)
        for what in res.degradations:
            self.s.degrade(what)
        if res.cov is not None:  # what the request policy reads at the next gate
            pos, rot = pose_cov_sigmas(res.cov)
            self.s.sigmas[other] = (float(rot), float(pos) if metric else float("nan"))
        if not metric:
            return self._unscaled(res, switch)
        # what the switch said about its own anchors does not describe the graph's estimate
        reason = join(*(r for r in split(switch[2]) if r not in _SWITCH_ONLY))
        if res.T_cj_ci is None:
            if res.expired:  # nothing confirmed yet and the newest node too old: said as the switch says it
                return "none", None, join(reason, "unverified-expired"), res.node_step, None
            if res.uninformative:  # predicted rotation sigma above graph.max_sigma_rot_rad (an odometry failure)
                return "none", None, join(reason, "graph-uninformative"), res.node_step, None
            return "none", None, reason or ("no-direct-estimate-yet" if direct is None else "graph-empty"), -1, None
        return "direct" if res.measured else "propagated", res.T_cj_ci, reason, res.node_step, res.cov

    @staticmethod
    def _unscaled(res: Any, switch: tuple) -> tuple[str, np.ndarray | None, str, int, np.ndarray | None]:
        """Without metric depth: the graph's rotation on the switch's estimate, where the switch has one."""
        source, T, reason, anchor_step = switch
        if T is None or res.T_cj_ci is None:
            return source, T, reason, anchor_step, None
        out = np.array(T, dtype=np.float64, copy=True)
        out[:3, :3] = res.T_cj_ci[:3, :3]
        cov = np.full((6, 6), np.nan)
        cov[:3, :3] = res.cov[:3, :3]  # the rotation block; the translation's scale is unknown
        return source, out, reason, anchor_step, cov

    def _relative(self, st: StepState, other: str) -> tuple[str, np.ndarray | None, str, int]:
        pose = self.s.poses.get(other)
        fresh = pose is not None and pose[0] == st.step
        pair = self.s.pairs.setdefault(other, PairAnchors(self.config.anchors))
        info = st.pair_info.setdefault(other, PairInfo())
        if fresh and self.config.anchors.verify and pair.track(st.step, self.s.X, pose[1]):
            self.s.degrade("anchor:odometry-jump")
        # the peer's estimate (share_estimates) only while the pair's anchor (if any) is not this robot's own:
        # it stands in where this robot cannot place the peer, it does not replace what this robot measured
        asked, shared = st.requested.get(other, self.gate.gate_open(other)), st.shared.get(other)
        late = other in st.landed and st.landed[other].step < st.step  # landed from an earlier step
        asked = asked or other in st.landed
        if pair.anchor is not None and not any(pair.anchor is a for a in self.s.shared_anchors.get(other, ())):
            shared = None
        if asked or shared is not None:
            ests, reason = self._directs(st, other) if asked else ([], "")
            if shared is not None:  # the peer's registration: another view of the pair (share_estimates)
                # first when it stands on more inliers than this robot's best: the one offered as the anchor
                ests = [shared] + ests if ests and 0 <= ests[0][3] < shared[3] else ests + [shared]
            if ests:
                via, T = ests[0][1], ests[0][2]
                info.direct_via, info.direct_T, info.direct_inliers = via, T, ests[0][3]
                plog = self.s.pose_logs.get(other)
                X_j = pose[1] if fresh else None if plog is None else plog.exact(st.step)
                bridged = X_j is None
                if bridged:  # the pose message is lost: bridge it (corrected when the next one comes)
                    X_j = None if plog is None else plog.bridged(st.step)
                    if X_j is None:
                        self.s.degrade("anchor:not-stored-pose-missing")
                        return "direct", T, "anchor-not-stored", st.step
                    self.s.degrade("pose:bridged")
                est = Anchor(st.step, T, self.s.X.copy(), X_j.copy(), self.odometer(self.s.robot_id, st.step, self.s.X),
                             self.s.odometers[other][2] if other in self.s.odometers else 0.0, st.metric_scale,
                             int(info.direct_inliers))
                if bridged:
                    plog.defer(st.step, est)
                if via == SHARED_VIA:  # remembered while it may become the anchor (a candidate that verifies late)
                    keep = int(self.config.anchors.candidate_steps) + 1
                    self.s.shared_anchors[other] = [a for a in self.s.shared_anchors.get(other, ())
                                                  if a is pair.anchor or st.step - a.step <= keep] + [est]
                if not self.config.anchors.verify:  # the paper: every direct estimate is the new anchor
                    pair.anchor, info.verdict = est, "unchecked"
                    return "direct", T, join(REASON_SHARED if via == SHARED_VIA else "",
                                             "registration-late" if late else ""), st.step
                others = [Anchor(st.step, T2, est.X_i, est.X_j, est.odo_i, est.odo_j, est.metric)
                          for k2, _, T2, _ in ests[1:] if k2 != ests[0][0]]
                check = pair.offer(est, others)
                info.verdict, info.check_rot_rad, info.check_trans_m = check.verdict, check.rot_rad, check.trans_m
                if check.verdict == "replaced":
                    self.s.degrade("anchor:replaced")
                for _ in check.dropped:  # unverified candidates the group that verified left out
                    self.s.degrade("anchor:inconsistent")
                # nothing agrees with it yet; a peer's estimate (share_estimates), which this robot could not
                # check by a registration of its own, is held until another estimate verifies it
                if check.verdict == "unverified" and (not self.config.anchors.report_unverified or via == SHARED_VIA):
                    return "none", None, "unverified-held", -1
                if check.verdict == "weak":  # agrees, but on too few inliers to replace the anchor
                    self.s.degrade("anchor:weak")
                    reason = "direct-weak"
                elif check.verdict not in NOT_REPORTED:  # accepted, verified, replaced, unverified
                    why = ("unverified" if check.verdict == "unverified" else "",
                           REASON_SHARED if via == SHARED_VIA else "", "registration-late" if late else "")
                    return "direct", T, join(*why), st.step
                else:
                    self.s.degrade("anchor:inconsistent")
                    reason = "direct-rejected"
        else:  # closed; say why when there was no score at all (lost, blank, mismatched)
            reason = f"request-skipped: {st.skipped[other]}" if other in st.skipped else st.gate_reason.get(other, "")
            if not self.config.backend.propagate:
                return "none", None, reason or "gate-closed", -1
        if not self.config.backend.propagate:
            return "none", None, reason, -1
        anchor, verified = pair.carried(st.step)
        if anchor is None:
            why = ("no-anchor" if not pair.candidates else
                   "unverified-expired" if self.config.anchors.report_unverified else "unverified-held")
            return "none", None, join(reason, why), -1
        if pose is None:
            return "none", None, join(reason, "no-pose-of-other"), -1
        X_j = pose[1]
        if not fresh:
            self.s.degrade("pose:stale")
            reason = join(reason, "stale-pose")
            plog = self.s.pose_logs.get(other)
            X_j = X_j if plog is None else plog.bridged(st.step)  # the last velocity carried on
        if not verified:
            reason = join(reason, "unverified")
        return "propagated", anchor.propagated(self.s.X, X_j), reason, anchor.step

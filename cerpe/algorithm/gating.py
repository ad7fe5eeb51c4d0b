"""Phases 2 (broadcast) and 3 (gate, request policy) of a robot: :class:`Gate`.

A collaborator of :class:`~cerpe.algorithm.agent.RobotAgent`: it reads and writes the robot's
:class:`~cerpe.algorithm.state.RobotState` (this step's scores, the keyframes, anchors and
odometers, what requests brought). Scores are cosines of ``[D]`` descriptors (or of a codec's
dequantised values).
"""
from __future__ import annotations

from typing import Mapping, Sequence

import numpy as np

from ..memory import Keyframe
from ..messages import DescriptorMessage, decode
from .direct import SHARED_VIA
from .policy import AskLog, PairView, after_request, decide, skip_for_shared

from ..compress import DescriptorCodec
from .config import AlgorithmConfig
from .state import PairInfo, RobotState, StepState, timed


class Gate:
    """Phases 2 and 3 of one robot over its :class:`~cerpe.algorithm.state.RobotState`.

    ``codec``: the compressed descriptor codec (None: the full descriptor); ``tau``: the gate
    threshold the scores are compared with (``gate.tau``, or the codec's own).
    """

    def __init__(self, state: RobotState, config: AlgorithmConfig, codec: DescriptorCodec | None, tau: float) -> None:
        self.s, self.config, self.codec, self.tau = state, config, codec, float(tau)

    # ---------------------------------------------------------------- 2. broadcast
    def descriptor_frame(self, dtype: str) -> bytes:
        """This step's descriptor as a wire frame; the quantised values are kept for scoring."""
        st = self.s.step_state()
        if self.codec is not None:
            msg = self.codec.message(self.s.index, st.step, st.descriptor)
            st.wire_descriptor = self.codec.dequantise(msg.descriptor)
            return msg.encode()
        frame = DescriptorMessage(self.s.index, st.step, st.descriptor, dtype).encode()
        st.wire_descriptor = decode(frame).descriptor
        return frame

    def received_values(self, msg: DescriptorMessage) -> tuple[np.ndarray | None, str]:
        """A received descriptor message -> the values the gate scores, or ``(None, fault)``."""
        if self.codec is not None:
            return self.codec.decode(msg)
        if msg.coded:
            return None, "codec-mismatch"
        return msg.descriptor, ""

    def _keyframe_values(self, kf: Keyframe) -> np.ndarray:
        """A keyframe's descriptor as the gate compares it: its codec values (cached per keyframe) or itself."""
        if self.codec is None:
            return kf.descriptor
        v = self.s.kf_wire.get(kf.step)
        if v is None:
            live = {k.step for k in self.s.memory.newest_first()}
            self.s.kf_wire = {s: w for s, w in self.s.kf_wire.items() if s in live}
            v = self.s.kf_wire[kf.step] = self.codec.wire(kf.descriptor)
        return v

    # ---------------------------------------------------------------- 3. gate
    def score_descriptor(self, other: str, descriptor: np.ndarray | DescriptorMessage | None) -> float:
        """Cosine score against a received descriptor (None: it did not arrive); records the gate decision.

        A :class:`~cerpe.messages.DescriptorMessage` is decoded first (a compressed one by
        this robot's codec); one of another codec or codebook, or whose code does not
        decode, is counted (``descriptor:<fault>``) and keeps the gate closed.

        Returns the score of the current frame (the paper's gate score), NaN when
        none can be computed (the gate stays closed and the reason is kept). The
        received descriptor is also scored against every keyframe; the best of all
        (and the keyframe that gave it) opens the gate with ``gate.memory_aware``.
        """
        return self.score_descriptors({other: descriptor})[other]

    def score_descriptors(self, received: Mapping[str, np.ndarray | DescriptorMessage | None]) -> dict[str, float]:
        """:meth:`score_descriptor` of every peer at once: the received descriptors are checked one by one
        (faults counted in the order given), then scored against the current frame and every keyframe
        in one matrix product (:func:`cosines`). Returns each peer's score of the current frame."""
        st = self.s.step_state()
        with timed(st, "gate", "gate_score"):
            ready: dict[str, np.ndarray] = {}
            for other, descriptor in received.items():
                st.scores[other] = float("nan")
                d, reason = self._received(st, other, descriptor)
                if reason:
                    st.gate_reason[other] = reason
                else:
                    ready[other] = d
            if ready:
                own = st.wire_descriptor if st.wire_descriptor is not None else st.descriptor
                kfs = self.s.memory.newest_first()
                cos = cosines([own] + [self._keyframe_values(kf) for kf in kfs], list(ready.values()))
                for p, other in enumerate(ready):
                    st.scores[other] = score = float(cos[0, p])
                    best = (score, -1)
                    if kfs:  # the best keyframe over the current frame (ties: the newest), as memory_scores
                        c = np.where(np.isnan(cos[1:, p]), -np.inf, cos[1:, p])
                        k = int(np.argmax(c))
                        if c[k] > score:
                            best = (float(c[k]), kfs[k].step)
                    st.memory_scores[other] = best
        return {other: st.scores[other] for other in received}

    def _received(self, st: StepState, other: str, descriptor: np.ndarray | DescriptorMessage | None
                  ) -> tuple[np.ndarray | None, str]:
        """``(values to score, "")`` of a received descriptor, or ``(None, reason)`` (faults counted)."""
        own = st.wire_descriptor if st.wire_descriptor is not None else st.descriptor
        reason = ""
        if isinstance(descriptor, DescriptorMessage):
            descriptor, fault = self.received_values(descriptor)
            if fault:
                self.s.degrade(f"descriptor:{fault}")
                return None, f"descriptor-{fault}"
        fresh = descriptor is not None
        if descriptor is None:  # lost: the peer's last one if recent, else the gate waits
            self.s.degrade("descriptor:missing")
            descriptor = self._recent_descriptor(other, st.step)
            if descriptor is None:
                return None, "descriptor-missing"
        if st.blank:
            return None, "own-descriptor-degenerate"
        d = np.asarray(descriptor, dtype=np.float32).ravel()
        if d.size != own.size:
            self.s.degrade("descriptor:wrong-length")
            reason = "descriptor-length-mismatch"
        elif not np.all(np.isfinite(d)) or not np.any(d):
            self.s.degrade("descriptor:other-zero-norm")
            reason = "other-descriptor-degenerate"
        elif fresh:
            self.s.last_descriptors[other] = (st.step, d)
        return (None, reason) if reason else (d, "")

    def peer_absent(self, other: str) -> None:
        """Online by stamps: ``other`` is not up; the gate stays closed (reason ``peer-absent``)."""
        st = self.s.step_state()
        st.scores[other] = float("nan")
        st.gate_reason[other] = "peer-absent"

    def peer_gone(self, other: str) -> None:
        """The link says ``other`` left: its last descriptor no longer stands in for a lost one."""
        self.s.last_descriptors.pop(other, None)

    def _recent_descriptor(self, other: str, step: int) -> np.ndarray | None:
        """``other``'s last descriptor when at most ``messages.stale_descriptor_steps`` steps old (counted
        ``descriptor:stale-used``: a lost one does not close the gate at once), else None."""
        last = self.s.last_descriptors.get(other)
        if last is None or not 0 < step - last[0] <= self.config.messages.stale_descriptor_steps:
            return None
        self.s.degrade("descriptor:stale-used")
        return last[1]

    def gate_open(self, other: str) -> bool:
        """``score >= gate_tau``: the current frame's score, or with ``gate.memory_aware`` the best over the keyframes
        too (``tau`` is ``gate.tau``, or the codec's own threshold with a compressed descriptor)."""
        s = self.gate_score(self.s.step_state(), other)
        return bool(np.isfinite(s) and s >= self.tau)

    def gate_score(self, st: StepState, other: str) -> float:
        """The score the gate compares with ``tau``: the current frame's, or with ``gate_memory`` the best over
        the keyframes too (NaN: none)."""
        s = st.scores.get(other, float("nan"))
        if self.config.gate.memory_aware and np.isfinite(s):
            s = st.memory_scores[other][0]
        return s

    def wants_image(self, other: str) -> bool:
        """Whether to request ``other``'s image this step: the gate and the request policy
        (:mod:`~cerpe.algorithm.policy`; the paper's asks whenever the gate opens; with ``share_estimates``
        the ``peer-shares`` rule may skip it). A skipped request is kept (``PairRecord.request_skipped``,
        reason ``request-skipped: <rule>``); the pair then propagates its anchor."""
        st = self.s.step_state()
        gate = self.gate_open(other)
        ask, why = self._decide(st, other)
        limit = int(self.config.policy.max_requests)
        if ask and limit > 0 and self._request_rank(st).get(other, 0) >= limit:
            ask, why = False, "max-requests"
        st.requested[other] = ask
        if gate and not ask:
            st.skipped[other] = why
        return ask

    def _decide(self, st: StepState, other: str) -> tuple[bool, str]:
        """The request policy's word on ``other`` this step, before the per-step limit."""
        conf = self.config.policy
        shares = bool(self.config.messages.share_estimates and conf.mode != "always")
        view = self.pair_view(other, st.step) if conf.mode == "pays" or shares else None
        ask, why = decide(conf, self.gate_open(other), view)
        if ask and shares and skip_for_shared(view):
            ask, why = False, "peer-shares"
        return ask, why

    def _request_rank(self, st: StepState) -> dict[str, int]:
        """Rank of each scored peer the policy would ask this step, highest gate score first (ties and NaN
        scores: in the order they were scored); ``policy.max_requests`` asks the first ones only."""
        if st.request_rank is None:
            order = list(st.scores)
            wanted = [o for o in order if self._decide(st, o)[0]]
            score = {o: self.gate_score(st, o) for o in wanted}
            key = {o: (-score[o] if np.isfinite(score[o]) else np.inf, order.index(o)) for o in wanted}
            st.request_rank = {o: r for r, o in enumerate(sorted(wanted, key=key.__getitem__))}
        return st.request_rank

    def note_request(self, other: str, info: PairInfo) -> None:
        """After the pass: what the request to ``other`` brought (:func:`~cerpe.algorithm.policy.after_request`).
        The image placed when this robot's own registration gave the estimate offered to anchor verification;
        with ``share_estimates`` a peer's estimate on more inliers is offered instead, and the request counts
        as a miss: its image added only a weaker second view (the ``peer-shares`` rule reads this)."""
        self.s.asks[other] = after_request(self.config.policy, self.s.asks.get(other), self.s.step_state().step,
                                         info.direct_T is not None and info.direct_via != SHARED_VIA,
                                         info.verdict, info.check_rot_rad)

    def pair_view(self, other: str, step: int) -> PairView:
        """What the request policy reads about a pair before this step's pass (anchors, odometers of
        the previous step, the graph's last sigma)."""
        pair = self.s.pairs.get(other)
        tries = self.s.asks.get(other, AskLog()).view(step)
        tries["steps_since_shared"] = step - self.s.shared_steps.get(other, -(1 << 30))
        if pair is None or pair.anchor is None:
            return PairView(anchored=False, pending=bool(pair and pair.candidates), **tries)
        a = pair.anchor
        odo = [self.s.odometers.get(r, (0, None, o))[2] for r, o in ((self.s.robot_id, a.odo_i), (other, a.odo_j))]
        rot, pos = self.s.sigmas.get(other, (float("nan"), float("nan")))
        return PairView(anchored=True, pending=bool(pair.challengers), steps_since=step - a.step,
                        travelled_m=abs(odo[0] - a.odo_i) + abs(odo[1] - a.odo_j),
                        sigma_rot_rad=rot, sigma_pos_m=pos, **tries)



def cosines(rows: Sequence[np.ndarray], cols: Sequence[np.ndarray]) -> np.ndarray:
    """``[len(rows), len(cols)]`` cosine similarities of 1-D vectors of one length, in float64 and clipped
    to [-1, 1]; NaN where either has zero or non-finite norm. What :func:`cerpe.memory.cosine` gives
    for each pair, from one matrix product (equal to it within float rounding)."""
    A = np.asarray(np.stack([np.asarray(r, np.float64).ravel() for r in rows]))
    B = np.asarray(np.stack([np.asarray(c, np.float64).ravel() for c in cols]))
    na, nb = np.linalg.norm(A, axis=1), np.linalg.norm(B, axis=1)
    with np.errstate(divide="ignore", invalid="ignore"):
        cos = np.clip((A @ B.T) / (na[:, None] * nb[None, :]), -1.0, 1.0)
    bad_a = ~((na > 0) & np.isfinite(na))
    bad_b = ~((nb > 0) & np.isfinite(nb))
    cos[bad_a, :] = np.nan
    cos[:, bad_b] = np.nan
    return cos

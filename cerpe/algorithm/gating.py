"""Phases 2 (broadcast) and 3 (gate, request policy) of a robot: :class:`Gate`.

A collaborator of :class:`~cerpe.algorithm.agent.RobotAgent`: it reads and writes the robot's
:class:`~cerpe.algorithm.state.RobotState` (this step's scores, the keyframes, anchors and
odometers, what requests brought). Scores are cosines of ``[D]`` descriptors (or of a codec's
dequantised values).
"""
from __future__ import annotations

import time
import numpy as np

from ..memory import Keyframe, cosine
from ..messages import DescriptorMessage, decode
from .direct import SHARED_VIA
from .policy import AskLog, PairView, after_request, decide, skip_for_shared

from ..compress import DescriptorCodec
from .config import AlgorithmConfig
from .state import PairInfo, RobotState


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
        st = self.s.step_state()
        t0 = time.perf_counter()
        own = st.wire_descriptor if st.wire_descriptor is not None else st.descriptor
        score, reason = float("nan"), ""
        if isinstance(descriptor, DescriptorMessage):
            descriptor, fault = self.received_values(descriptor)
            if fault:
                self.s.degrade(f"descriptor:{fault}")
                reason = f"descriptor-{fault}"
        fresh = descriptor is not None
        if not reason and descriptor is None:  # lost: the peer's last one if recent, else the gate waits
            self.s.degrade("descriptor:missing")
            descriptor = self._recent_descriptor(other, st.step)
            if descriptor is None:
                reason = "descriptor-missing"
        if reason:
            pass  # counted above
        elif st.blank:
            reason = "own-descriptor-degenerate"
        else:
            d = np.asarray(descriptor, dtype=np.float32).ravel()
            if d.size != own.size:
                self.s.degrade("descriptor:wrong-length")
                reason = "descriptor-length-mismatch"
            elif not np.all(np.isfinite(d)) or not np.any(d):
                self.s.degrade("descriptor:other-zero-norm")
                reason = "other-descriptor-degenerate"
            else:
                score = cosine(own, d)
                if fresh:
                    self.s.last_descriptors[other] = (st.step, d)
                best = (score, -1)
                for kf in self.s.memory.newest_first():
                    c = cosine(self._keyframe_values(kf), d)
                    if c > best[0]:
                        best = (c, kf.step)
                st.memory_scores[other] = best
        st.scores[other] = score
        if reason:
            st.gate_reason[other] = reason
        st.timings["gate"] += time.perf_counter() - t0
        return score

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
        st = self.s.step_state()
        s = st.scores.get(other, float("nan"))
        if self.config.gate.memory_aware and np.isfinite(s):
            s = st.memory_scores[other][0]
        return bool(np.isfinite(s) and s >= self.tau)

    def wants_image(self, other: str) -> bool:
        """Whether to request ``other``'s image this step: the gate and the request policy
        (:mod:`~cerpe.algorithm.policy`; the paper's asks whenever the gate opens; with ``share_estimates``
        the ``peer-shares`` rule may skip it). A skipped request is kept (``PairRecord.request_skipped``,
        reason ``request-skipped: <rule>``); the pair then propagates its anchor."""
        st = self.s.step_state()
        gate = self.gate_open(other)
        conf = self.config.policy
        shares = bool(self.config.messages.share_estimates and conf.mode != "always")
        view = self.pair_view(other, st.step) if conf.mode == "pays" or shares else None
        ask, why = decide(conf, gate, view)
        if ask and shares and skip_for_shared(view):
            ask, why = False, "peer-shares"
        st.requested[other] = ask
        if gate and not ask:
            st.skipped[other] = why
        return ask

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


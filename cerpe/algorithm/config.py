"""The algorithm's part of the configuration tree (:class:`AlgorithmConfig`) and the algorithm's exception.

One group per phase of Algorithm 1: ``gate``, ``memory``, ``scale``, ``odometry``, ``anchors``,
``policy`` (when a gate that opened asks for the image), ``backend`` (switch or pose graph),
``messages`` (what goes on the wire) and ``stamps`` (robots online at their own pace: a peer's
descriptor and pose at this robot's frame's stamp). The whole tree, with the plug-ins' ``backbone`` group and the
named presets, is :class:`cerpe.method_config.CerpeConfig`. Thresholds on descriptor similarity are
specific to a descriptor: ``None`` takes the descriptor's own calibrated value, else the paper's
(:data:`PAPER_THRESHOLDS`, calibrated for SALAD); :meth:`AlgorithmConfig.resolved` applies this.
"""
from __future__ import annotations

import dataclasses
from dataclasses import dataclass

from ..compress import CODECS as DESCRIPTOR_CODECS
from ..errors import CerpeError
from ..knobs import Group, group, knob
from ..memory import MemoryConfig
from ..messages import DESCRIPTOR_DTYPES, REPLY_CODECS
from ..scale import StepLengthRule
from .anchors import AnchorConfig
from .graph_model import GraphConfig
from .policy import PolicyConfig

PAPER_THRESHOLDS: dict[str, float] = {"tau": 0.2, "tau_m": 0.9, "tau_k": 0.2}
BACKENDS: tuple[str, ...] = ("switch", "graph")


class AlgorithmError(CerpeError, ValueError):
    """Malformed input to the algorithm (names robot, step and field)."""


@dataclass(frozen=True)
class GateConfig(Group):
    """Phase 3: when a received descriptor opens the gate."""

    tau: float | None = knob(None, "a received descriptor whose cosine similarity reaches this opens the gate "
                             "(None: the descriptor's calibrated value)", low=-1.0, high=1.0)
    memory_aware: bool = knob(True, "score a received descriptor against the keyframes too and open on the best "
                              "(False: the paper's gate, the current frame only)")


@dataclass(frozen=True)
class ScaleConfig(Group):
    """Phase 5: the metric scale of a pass."""

    metric_unit: bool = knob(True, "a pass whose unit is already the metre (BackboneOutput.metric_unit) takes "
                             "s = 1 (False: always the paper's median depth ratio)")
    min_pixels: int = knob(25, "valid depth pixels a keyframe needs to vote in the scale (pixels)", low=1)


@dataclass(frozen=True)
class OdometryConfig(Group):
    """Phase 6: the robot's metric odometry ``X``."""

    track_previous: bool = knob(True, "hand the previous frame to the pass too and chain ego-motion through it "
                                "(False: the paper's pass, keyframes only)")
    max_accel_mps2: float = knob(5.0, "hold a step that slows down faster than the platform can brake "
                                 "(m/s^2; 0: off)", low=0.0)

    def step_rule(self) -> StepLengthRule:
        """The odometry's step-length rule (:class:`cerpe.scale.StepLengthRule`)."""
        return StepLengthRule(max_accel_mps2=float(self.max_accel_mps2))


@dataclass(frozen=True)
class BackendConfig(Group):
    """Phase 8: the relative pose reported per pair."""

    kind: str = knob("switch", "switch: a direct estimate, else the last anchor propagated (the paper); graph: a "
                     "robust pose graph per pair over every direct estimate and both odometries (ours)",
                     choices=BACKENDS)
    propagate: bool = knob(True, "propagate the last anchor while there is no direct estimate (False: the paper's "
                           "CERPE w/o EM)")
    graph: GraphConfig = group(GraphConfig, "the pose graph (kind: graph)")


@dataclass(frozen=True)
class MessageConfig(Group):
    """What robots put on the wire."""

    descriptor_dtype: str = knob("fp16", "precision of the full descriptor on the wire (fp16: the paper's size)",
                                 choices=DESCRIPTOR_DTYPES)
    descriptor_codec: str = knob("full", "full: every descriptor value (the paper); pca-int8, pca-pq: a fitted "
                                 "projection, then int8 or product quantisation (ours)",
                                 choices=("full", *DESCRIPTOR_CODECS))
    projection: str | None = knob(None, "the compressed codecs' projection file (None: the shipped one, fitted for "
                                  "the offline descriptor)")
    codec_tau: float | None = knob(None, "gate threshold on compressed scores (None: the codec's calibrated value, "
                                   "else gate.tau)", low=-1.0, high=1.0)
    reply_codec: str = knob("jpeg", "image reply codec (jpeg: the paper's; -grey: the channels' mean)",
                            choices=REPLY_CODECS)
    reply_quality: int = knob(90, "image reply quality (0-100)", low=0, high=100)
    reply_scale: float = knob(1.0, "image replies are downsized by this factor, intrinsics alike (1: full "
                              "resolution)", low=0.0, low_open=True, high=1.0)
    request_retries: int = knob(2, "image requests sent again within the step when no reply came (lost)", low=0)
    stale_descriptor_steps: int = knob(1, "a lost descriptor is replaced by the peer's last one at most this many "
                                       "steps old (0: the gate waits)", low=0)
    share_estimates: bool = knob(False, "ours: also broadcast this step's direct estimates (62 B each); a robot "
                                 "takes its peer's where it placed nothing, or to verify its own")


@dataclass(frozen=True)
class StampsConfig(Group):
    """Online by capture stamps: what a robot takes of a peer at its own frame's stamp (cerpe online)."""

    max_descriptor_age_s: float = knob(1.0, "a peer's descriptor is scored against this frame when its stamp is at "
                                       "most this far from the frame's (s)", low=0.0)
    max_pose_gap_s: float = knob(1.0, "a peer's pose at this frame's stamp is interpolated between two of its poses at "
                                 "most this far apart (s)", low=0.0, low_open=True)
    max_extrapolation_s: float = knob(1.0, "or extrapolated at its last velocity at most this far past its newest "
                                      "pose (s); further: unknown, nothing propagated", low=0.0)


@dataclass(frozen=True)
class AlgorithmConfig(Group):
    """Every knob Algorithm 1 reads, one group per phase (see the module docstring)."""

    gate: GateConfig = group(GateConfig, "phase 3: when a received descriptor opens the gate")
    memory: MemoryConfig = group(MemoryConfig, "phase 9: the bounded keyframe memory")
    scale: ScaleConfig = group(ScaleConfig, "phase 5: the metric scale of a pass")
    odometry: OdometryConfig = group(OdometryConfig, "phase 6: the robot's metric odometry")
    anchors: AnchorConfig = group(AnchorConfig, "phase 8: when a direct estimate becomes the pair's anchor")
    policy: PolicyConfig = group(PolicyConfig, "phase 3: when a gate that opened asks for the image")
    backend: BackendConfig = group(BackendConfig, "phase 8: switch or pose graph")
    messages: MessageConfig = group(MessageConfig, "what robots put on the wire")
    stamps: StampsConfig = group(StampsConfig, "online by capture stamps: a peer's frames at this robot's frame's stamp")

    def resolved(self, descriptor_thresholds: dict[str, float] | None = None) -> "AlgorithmConfig":
        """Concrete ``gate.tau``, ``memory.tau_m``, ``memory.tau_k``: a value set here > the descriptor's
        calibration > the paper's. Idempotent on concrete values."""
        given = dict(descriptor_thresholds or {})

        def pick(own: float | None, name: str) -> float:
            return float(own if own is not None else given.get(name, PAPER_THRESHOLDS[name]))

        gate = dataclasses.replace(self.gate, tau=pick(self.gate.tau, "tau"))
        memory = dataclasses.replace(self.memory, tau_m=pick(self.memory.tau_m, "tau_m"),
                                     tau_k=pick(self.memory.tau_k, "tau_k"))
        return dataclasses.replace(self, gate=gate, memory=memory)

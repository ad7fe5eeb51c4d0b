"""Parameters of the method (:class:`CerpeConfig`) and the algorithm's exception."""
from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field

import numpy as np

from ..errors import CerpeError
from ..memory import MemoryConfig
from ..compress import CODECS as DESCRIPTOR_CODECS
from ..messages import DESCRIPTOR_DTYPES, REPLY_CODECS
from ..scale import ScaleError, StepLengthRule
from .anchors import AnchorConfig
from .graph import GraphConfig
from .policy import PolicyConfig

PAPER_THRESHOLDS: dict[str, float] = {"tau": 0.2, "tau_m": 0.9, "tau_k": 0.2}
BACKENDS: tuple[str, ...] = ("switch", "graph")
# Smaller messages chosen on development data (not the paper's protocol, which is CerpeConfig's
# default): the int8 descriptor codec (gate ROC AUC within 0.01 of the full descriptor,
# lab/descriptor_codec_auc.py) and WebP-75 full-resolution replies (lab/reply_codecs.py:
# 36 % of JPEG-90's bytes, the same placements). CerpeConfig(**COMPRESSED_MESSAGES) selects them.
COMPRESSED_MESSAGES: dict[str, object] = {"descriptor_codec": "pca-int8", "reply_codec": "webp",
                                          "reply_quality": 75, "reply_scale": 1.0}
# Ours at its leanest (chosen on development data by lab/policy.py, figures in the commits
# that set it): the request policy "pays" that also backs off from gates whose images do not place (after
# 3 misses: every 3 steps, every 2 for a pair without an anchor, never while estimates wait to
# verify) and asks once more when the estimate that set the anchor disagreed by more than 0.03 rad with what
# verified it (lab/policy.py "lean-pe-u2-rc-l1"; dev, pooled: 0.095 of always-send's bytes, e_rot
# 0.90 x and success 0.984 x the paper protocol's, where LEAN_V1 gave 0.084 / 1.08 x / 0.945 x; after 2
# misses, "-b2": 0.089 / 0.97 x / 0.989 x, but cad-s1 e00's e_rot 1.03 x -> 1.66 x),
# over COMPRESSED_MESSAGES with grey WebP-75 replies (the channels' mean: all the offline backbone reads of a
# received image; lab/reply_codecs.py: the same placements at 81 % of colour WebP-75's bytes).
# CerpeConfig(**LEAN) selects it; the Pareto settings of `make paper` run it. LEAN_V1_POLICY: LEAN before.
LEAN_V1_POLICY: dict[str, object] = {"mode": "pays", "miss_limit": 3, "miss_backoff_steps": 3}
LEAN_POLICY: dict[str, object] = {"mode": "pays", "miss_limit": 3, "miss_backoff_steps": 3, "unanchored_backoff_steps": 2,
                                  "backoff_pending_exempt": True, "recheck_rot_rad": 0.03, "recheck_limit": 1}
LEAN: dict[str, object] = {"request_policy": LEAN_POLICY, **COMPRESSED_MESSAGES, "reply_codec": "webp-grey"}


class AlgorithmError(CerpeError, ValueError):
    """Malformed input to the algorithm (names robot, step and field)."""


@dataclass(frozen=True)
class CerpeConfig:
    """All parameters of the method.

    Thresholds (``tau`` gate, ``tau_m``/``tau_k`` keyframe rule) are cosine
    similarities and therefore specific to a descriptor. Precedence, highest
    first: a value set here explicitly (not None) > the descriptor's
    ``thresholds`` dict (its own calibration) > the paper's values
    (:data:`PAPER_THRESHOLDS`, calibrated for SALAD). :meth:`resolved` applies
    this and returns a config with concrete numbers (what a team uses and a run
    records).

    Attributes:
        tau: gate threshold; ``score >= tau`` requests the collaborator's image.
        tau_m, tau_k, delta_k, memory_capacity: keyframe rule, see
            :class:`cerpe.memory.MemoryConfig` (``memory_capacity`` is the paper's L).
        propagate: False is the paper's "CERPE w/o EM": only direct estimates.
        descriptor_dtype: wire precision (``fp16``: the paper's message size; ``fp32``, ``int8``).
        jpeg_quality: quality of image replies (OpenCV scale 0-100).
        descriptor_codec: ``full`` (the paper's protocol: every descriptor value at
            ``descriptor_dtype``), or a compressed codec of :mod:`cerpe.compress`
            (``pca-int8``, ``pca-pq``: a fitted projection, then int8 / product
            quantisation; the gate scores the decoded values, the keyframe rule keeps
            the full descriptor).
        descriptor_projection: the projection file of the compressed codecs (None: the
            shipped ``cerpe/data/xfeat_salad_projection.npz``, fitted for the offline descriptor).
        descriptor_codec_tau: the gate threshold on compressed scores (None: the codec's
            calibrated value stored in the projection file, else ``tau``).
        reply_codec: image reply codec, ``jpeg`` (the paper's), ``webp``, or one of their
            single-channel forms ``jpeg-grey``, ``webp-grey`` (the channels' mean: all the
            offline backbone's XFeat features see of a colour image).
        reply_quality: its quality 0-100 (None: ``jpeg_quality``).
        reply_scale: image replies are downsized by this factor (1: full resolution, the
            paper's), intrinsics scaled alike.
        request_retries: image requests sent again, within the step, to a peer whose reply
            did not come (request or reply lost; counted ``msg:request-retried``); 0: never. No
            effect without loss; under loss a pair without an anchor has no other way to get one.
        descriptor_max_age: when a peer's descriptor of this step is lost, the gate scores
            its last one received if at most this many steps old (counted
            ``descriptor:stale-used``; co-visibility changes little in a step); 0: the
            gate stays closed until the next one arrives. No effect without loss.
        min_scale_pixels: valid depth pixels a keyframe needs to vote in the scale.
        unit_scale_without_depth: with no metric depth at all (depth source ``none``)
            use s = 1 instead of giving up (counted ``scale:unit-no-depth``); such runs
            are evaluated with ground-truth-scale translation only.
        ego_max_accel_mps2, ego_max_step_ratio, ego_step_noise_m, ego_step_window,
            ego_step_min_history: the step-length rule of the odometry
            (:class:`cerpe.scale.StepLengthRule`): a step slower than the median speed of the
            last ``window`` accepted steps by more than the ratio and than braking at the
            acceleration (plus the noise) allows is held at that speed (counted
            ``ego:step-held``); acceleration 0: off.
        track_previous: also hand the previous frame (with its metric depth) to the
            joint pass and compose the odometry from the previous-to-current increment
            (METHOD.md 2); the newest keyframe is the fallback. False is the paper's
            pass, ``[current] + keyframes (+ collaborators)``.
        backbone_metric_unit: when a pass says its unit is already the metre
            (:attr:`BackboneOutput.metric_unit`), use s = 1 instead of estimating a
            value that is 1 up to the keyframes' pose noise. False always runs
            METHOD.md step 4.
        min_image_std: grey-level standard deviation below which a frame is blank
            (black, white, constant grey), whatever the descriptor says.
        gate_memory: score a received descriptor against the current frame AND the
            keyframes; the gate opens when the best score passes ``tau`` (a
            collaborator seeing what this robot saw earlier is then registered
            against that keyframe). False is the paper's gate (current frame only).
        verify_anchors: a direct estimate becomes the pair's anchor only when
            something independent agrees (:mod:`cerpe.algorithm.anchors`): the
            propagated anchor, a second registration of the same step, or a recent
            unverified estimate. False is the paper's switching: every direct
            estimate is the new anchor.
        anchor_rot_tol_rad, anchor_trans_tol_m: how far an estimate may be from the
            anchor propagated to it right after that anchor (radians, metres).
        anchor_rot_drift_per_step: added to the rotation tolerance per step since the anchor.
        anchor_trans_drift_frac: added to the translation tolerance per metre the two
            robots travelled since the anchor (odometers summed).
        anchor_trans_rel: added to the translation tolerance per metre between the cameras.
        anchor_min_inliers: with an anchor, a direct estimate that agrees with it but
            stands on fewer registration inliers than this (when the backbone reports them)
            is *weak*: neither reported nor the new anchor, the anchor is propagated
            instead (counted ``anchor:weak``; 0: off). One that disagrees is judged as any
            other. 40: below it the appearance check already judges a placement.
        anchor_replace_after: when this many rejected estimates of the last
            ``anchor_candidate_steps`` steps agree with the newest of them (it included),
            the newest replaces the anchor.
        max_unverified_steps: before any anchor is verified, an unverified estimate is
            reported at its step and propagated for at most this many steps (only with
            ``report_unverified``).
        anchor_max_odo_rot_step: when either robot's odometry turns by more than this
            (radians per step) between two steps, the pair forgets its anchor and
            candidates (a lost track would carry them wrong; counted
            ``anchor:odometry-jump``); 0 turns the check off.
        report_unverified: whether a direct estimate that nothing has verified yet (no
            anchor, no agreeing second estimate) is reported; False holds it (source
            ``none``, reason ``unverified-held``) until something agrees with it.
        anchor_candidate_steps: how many steps an unverified estimate (or a rejected
            one) stays available to verify a later one.
        anchor_verify_support: without an anchor and without a second registration, the
            largest group of the recent unverified estimates (of the last
            ``anchor_candidate_steps`` steps, the new one included) that agree pairwise in
            rotation and translation verifies when it has this many members besides its
            newest, which becomes the anchor; the others are rejected
            (:func:`cerpe.algorithm.anchors.consensus`).
        anchor_verify_fraction: and when the recent estimates that agree with all of the
            group in rotation are at least this fraction of the others (0: any number;
            estimates that keep disagreeing with each other verify nothing; one off only
            in translation does not count against a group).
        registration_agree_rot_rad, registration_agree_trans_m: two registrations of
            one step through different own views agree (and verify each other) within
            these (the translation tolerance grows by ``anchor_trans_rel`` per metre
            between the cameras, as the anchor check's).
        backend: ``switch`` is the paper's estimate (a direct estimate, else the anchor
            propagated); ``graph`` (not in the paper: ``cerpe-graph``) reports each pair's
            robust pose graph over every direct estimate and both odometries, with its
            covariance (:mod:`cerpe.algorithm.graph`). The messages are the same.
        graph: the graph's noise models, kernel and window (:class:`~cerpe.algorithm.graph.GraphConfig`;
            a dict of its fields is accepted).
        request_policy: when a gate that opened asks for the image
            (:class:`~cerpe.algorithm.policy.PolicyConfig`; a dict of its fields is accepted):
            ``mode="gate"`` is the paper's (always), ``"pays"`` ours (only without a fresh,
            certain anchor), ``"always"`` every peer at every step.
        share_estimates: our extension, off in the paper's rows: after its pose, each robot
            broadcasts the direct estimates it made this step (an ``estimate`` frame, 62 B per
            estimate). Registration is not symmetric: a robot places a peer's image through the
            keyframes it kept, and a peer that passes where this robot was has no view of it. A
            robot whose own pass placed nothing of a peer then takes the peer's estimate,
            inverted, as its direct estimate of the pair (``direct_via`` -2; anchor verification
            judges it as its own, but an unverified one is held, not reported); with its own, the
            peer's is a second, independent registration that can verify it (and the one offered
            as the anchor when it has more inliers than the robot's best). Not taken: one on fewer
            than ``anchor_min_inliers`` inliers, and any while the pair's anchor is the robot's own
            measurement (its own estimates outrank the peer's; an anchor a shared estimate set is
            replaced by newer shared ones as its own by its own). ``request_policy.shared_skip_misses``
            then spares the replies a robot cannot place
            (:func:`~cerpe.algorithm.policy.skip_for_shared`).
    """

    tau: float | None = None
    tau_m: float | None = None
    tau_k: float | None = None
    delta_k: int = 3
    memory_capacity: int = 5
    propagate: bool = True
    descriptor_dtype: str = "fp16"
    jpeg_quality: int = 90
    descriptor_codec: str = "full"
    descriptor_projection: str | None = None
    descriptor_codec_tau: float | None = None
    reply_codec: str = "jpeg"
    reply_quality: int | None = None
    reply_scale: float = 1.0
    request_retries: int = 2
    descriptor_max_age: int = 1
    min_scale_pixels: int = 25
    unit_scale_without_depth: bool = False
    track_previous: bool = True
    ego_max_accel_mps2: float = 5.0
    ego_max_step_ratio: float = 2.0
    ego_step_noise_m: float = 0.05
    ego_step_window: int = 5
    ego_step_min_history: int = 3
    backbone_metric_unit: bool = True
    min_image_std: float = 2.0
    gate_memory: bool = True
    verify_anchors: bool = True
    anchor_rot_tol_rad: float = 0.15
    anchor_trans_tol_m: float = 0.3
    anchor_rot_drift_per_step: float = 0.005
    anchor_trans_drift_frac: float = 0.1
    anchor_trans_rel: float = 0.2
    anchor_min_inliers: int = 40
    anchor_replace_after: int = 5
    max_unverified_steps: int = 2
    anchor_candidate_steps: int = 10
    registration_agree_rot_rad: float = 0.15
    registration_agree_trans_m: float = 0.3
    anchor_verify_support: int = 2
    anchor_verify_fraction: float = 0.5
    anchor_max_odo_rot_step: float = 1.0
    report_unverified: bool = True
    share_estimates: bool = False
    backend: str = "switch"
    graph: GraphConfig = field(default_factory=GraphConfig)
    request_policy: PolicyConfig = field(default_factory=PolicyConfig)

    def __post_init__(self) -> None:
        if not isinstance(self.share_estimates, (bool, np.bool_)):
            raise AlgorithmError(f"config: share_estimates must be true or false, got {self.share_estimates!r}")
        if self.backend not in BACKENDS:
            raise AlgorithmError(f"config: backend must be one of {list(BACKENDS)}, got {self.backend!r}")
        for name, cls in (("graph", GraphConfig), ("request_policy", PolicyConfig)):
            self._sub_config(name, cls)
        for name in ("tau", "tau_m", "tau_k"):
            v = getattr(self, name)
            if v is not None and not (np.isfinite(v) and -1.0 <= v <= 1.0):
                raise AlgorithmError(f"config: {name} must be a cosine in [-1, 1], got {v}")
        if self.descriptor_dtype not in DESCRIPTOR_DTYPES:
            raise AlgorithmError(f"config: descriptor_dtype must be one of {list(DESCRIPTOR_DTYPES)}, "
                                 f"got {self.descriptor_dtype!r}")
        if not (0 <= int(self.jpeg_quality) <= 100):
            raise AlgorithmError(f"config: jpeg_quality must be in 0..100, got {self.jpeg_quality}")
        if self.descriptor_codec not in ("full", *DESCRIPTOR_CODECS):
            raise AlgorithmError(f"config: descriptor_codec must be one of {['full', *DESCRIPTOR_CODECS]}, "
                                 f"got {self.descriptor_codec!r}")
        v = self.descriptor_codec_tau
        if v is not None and not (np.isfinite(v) and -1.0 <= v <= 1.0):
            raise AlgorithmError(f"config: descriptor_codec_tau must be a cosine in [-1, 1], got {v}")
        if self.reply_codec not in REPLY_CODECS:
            raise AlgorithmError(f"config: reply_codec must be one of {list(REPLY_CODECS)}, got {self.reply_codec!r}")
        if self.reply_quality is not None and not (0 <= int(self.reply_quality) <= 100):
            raise AlgorithmError(f"config: reply_quality must be in 0..100, got {self.reply_quality}")
        if not (np.isfinite(self.reply_scale) and 0.0 < self.reply_scale <= 1.0):
            raise AlgorithmError(f"config: reply_scale must be in (0, 1], got {self.reply_scale}")
        for name in ("request_retries", "descriptor_max_age"):
            if int(getattr(self, name)) < 0:
                raise AlgorithmError(f"config: {name} must be >= 0, got {getattr(self, name)}")
        if int(self.min_scale_pixels) < 1:
            raise AlgorithmError(f"config: min_scale_pixels must be >= 1, got {self.min_scale_pixels}")
        self.step_rule()  # checks the step-length rule's values
        if not (np.isfinite(self.min_image_std) and self.min_image_std >= 0):
            raise AlgorithmError(f"config: min_image_std must be finite and >= 0, got {self.min_image_std}")
        for name in ("anchor_rot_tol_rad", "anchor_trans_tol_m", "anchor_rot_drift_per_step",
                     "anchor_trans_drift_frac", "anchor_trans_rel", "registration_agree_rot_rad",
                     "registration_agree_trans_m", "anchor_max_odo_rot_step"):
            v = getattr(self, name)
            if not (np.isfinite(v) and v >= 0):
                raise AlgorithmError(f"config: {name} must be finite and >= 0, got {v}")
        if not (np.isfinite(self.anchor_verify_fraction) and 0.0 <= self.anchor_verify_fraction <= 1.0):
            raise AlgorithmError(f"config: anchor_verify_fraction must be in [0, 1], got {self.anchor_verify_fraction}")
        for name in ("anchor_replace_after", "anchor_verify_support", "max_unverified_steps",
                     "anchor_candidate_steps", "anchor_min_inliers"):
            v, low = getattr(self, name), int(name in ("anchor_replace_after", "anchor_verify_support"))
            if int(v) != v or v < low:
                raise AlgorithmError(f"config: {name} must be an integer >= {low}, got {v}")

    def _sub_config(self, name: str, cls: type) -> None:
        """A nested config given as a dict of its fields becomes ``cls``; anything else but ``cls`` is an error."""
        value = getattr(self, name)
        if isinstance(value, dict):
            known = {f.name for f in dataclasses.fields(cls)}
            if set(value) - known:
                raise AlgorithmError(f"config: unknown {name} field(s) {sorted(set(value) - known)}; "
                                     f"known: {sorted(known)}")
            object.__setattr__(self, name, cls(**value))
        elif not isinstance(value, cls):
            raise AlgorithmError(f"config: {name} must be a {cls.__name__} or a dict, got {type(value).__name__}")

    def resolved(self, descriptor_thresholds: dict[str, float] | None = None) -> "CerpeConfig":
        """Concrete thresholds: explicit value > descriptor calibration > paper."""
        given = dict(descriptor_thresholds or {})
        vals = {}
        for name, paper in PAPER_THRESHOLDS.items():
            own = getattr(self, name)
            vals[name] = float(own if own is not None else given.get(name, paper))
        out = dataclasses.replace(self, **vals)
        out.memory_config()  # validates tau_k <= tau_m etc.
        return out

    def memory_config(self) -> MemoryConfig:
        r = self if self.tau_m is not None and self.tau_k is not None else self.resolved()
        return MemoryConfig(tau_m=r.tau_m, tau_k=r.tau_k, delta_k=self.delta_k, capacity=self.memory_capacity)

    def step_rule(self) -> StepLengthRule:
        """The odometry's step-length rule (:class:`cerpe.scale.StepLengthRule`)."""
        try:
            return StepLengthRule(max_ratio=float(self.ego_max_step_ratio), max_accel_mps2=float(self.ego_max_accel_mps2),
                                  noise_m=float(self.ego_step_noise_m), window=int(self.ego_step_window),
                                  min_history=int(self.ego_step_min_history))
        except ScaleError as exc:
            raise AlgorithmError(f"config: ego step rule: {exc}") from None

    def anchor_config(self) -> AnchorConfig:
        """The tolerances of anchor verification (:mod:`cerpe.algorithm.anchors`)."""
        return AnchorConfig(rot_tol_rad=self.anchor_rot_tol_rad, trans_tol_m=self.anchor_trans_tol_m,
                            rot_drift_per_step=self.anchor_rot_drift_per_step,
                            trans_drift_frac=self.anchor_trans_drift_frac, trans_rel=self.anchor_trans_rel,
                            replace_after=int(self.anchor_replace_after),
                            min_inliers=int(self.anchor_min_inliers),
                            max_unverified_steps=int(self.max_unverified_steps),
                            candidate_steps=int(self.anchor_candidate_steps),
                            agree_rot_rad=self.registration_agree_rot_rad,
                            agree_trans_m=self.registration_agree_trans_m,
                            verify_support=int(self.anchor_verify_support),
                            verify_fraction=float(self.anchor_verify_fraction),
                            max_odo_rot_step=float(self.anchor_max_odo_rot_step),
                            report_unverified=bool(self.report_unverified))

    def as_dict(self) -> dict:
        return dataclasses.asdict(self)

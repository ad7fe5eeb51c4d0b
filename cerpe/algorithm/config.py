"""Parameters of the method (:class:`CerpeConfig`) and the algorithm's exception."""
from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import numpy as np

from ..errors import CerpeError
from ..memory import MemoryConfig
from ..messages import DESCRIPTOR_DTYPES

PAPER_THRESHOLDS: dict[str, float] = {"tau": 0.2, "tau_m": 0.9, "tau_k": 0.2}


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
        min_scale_pixels: valid depth pixels a keyframe needs to vote in the scale.
        unit_scale_without_depth: with no metric depth at all (depth source ``none``)
            use s = 1 instead of giving up (counted ``scale:unit-no-depth``); such runs
            are evaluated with ground-truth-scale translation only.
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
    """

    tau: float | None = None
    tau_m: float | None = None
    tau_k: float | None = None
    delta_k: int = 3
    memory_capacity: int = 5
    propagate: bool = True
    descriptor_dtype: str = "fp16"
    jpeg_quality: int = 90
    min_scale_pixels: int = 25
    unit_scale_without_depth: bool = False
    track_previous: bool = True
    backbone_metric_unit: bool = True
    min_image_std: float = 2.0

    def __post_init__(self) -> None:
        for name in ("tau", "tau_m", "tau_k"):
            v = getattr(self, name)
            if v is not None and not (np.isfinite(v) and -1.0 <= v <= 1.0):
                raise AlgorithmError(f"config: {name} must be a cosine in [-1, 1], got {v}")
        if self.descriptor_dtype not in DESCRIPTOR_DTYPES:
            raise AlgorithmError(f"config: descriptor_dtype must be one of {list(DESCRIPTOR_DTYPES)}, "
                                 f"got {self.descriptor_dtype!r}")
        if not (0 <= int(self.jpeg_quality) <= 100):
            raise AlgorithmError(f"config: jpeg_quality must be in 0..100, got {self.jpeg_quality}")
        if int(self.min_scale_pixels) < 1:
            raise AlgorithmError(f"config: min_scale_pixels must be >= 1, got {self.min_scale_pixels}")
        if not (np.isfinite(self.min_image_std) and self.min_image_std >= 0):
            raise AlgorithmError(f"config: min_image_std must be finite and >= 0, got {self.min_image_std}")

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

    def as_dict(self) -> dict:
        return dataclasses.asdict(self)

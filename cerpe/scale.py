"""Metric scale of a joint backbone pass (paper Eq. scale, METHOD.md step 4).

    s = (1/K) * sum_k median_p ( Dstar_k(p) / D_k(p) )

``Dstar_k`` is the metric depth reference of keyframe k (sensor, dataset or a
metric-depth network) and ``D_k`` the backbone's up-to-scale depth of the same
frame from the current pass. Multiplying the pass's translations by ``s`` makes
them metres.

Robustness (the paper leaves these open):

* A pixel is valid when both depths are finite and > 0 and, if given, its backbone
  confidence is > 0. Invalid pixels are ignored, never divided by.
* A keyframe with fewer than ``min_pixels`` valid pixels (or without a reference at
  all) is skipped and reported; the mean runs over the remaining keyframes.
* No usable keyframe: ``scale`` is NaN with the reasons; the caller decides what to
  do (the algorithm falls back to its last valid scale).
* The metric map may have another resolution than the backbone's depth (sensors
  and networks rarely use the backbone's input size). It is resampled to the
  backbone depth's shape with nearest neighbour on pixel centres (no
  interpolation: averaging a 0 = unknown pixel with a valid one would invent depth).
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Sequence

import numpy as np

from .errors import CerpeError

DEFAULT_MIN_PIXELS = 100


class ScaleError(CerpeError, ValueError):
    """Malformed depth input (wrong dimensionality, mismatched lists)."""


@dataclass
class ScaleEstimate:
    """Result of :func:`recover_scale`.

    Attributes:
        scale: metres per backbone unit; NaN when no keyframe was usable.
        medians: ``[K]`` per-keyframe median ratio, NaN for skipped keyframes.
        n_valid_pixels: ``[K]`` valid pixel count per keyframe.
        n_used: number of keyframes averaged.
        skipped: ``(index, reason)`` per skipped keyframe; reasons are
            ``no-metric-depth``, ``no-backbone-depth``, ``too-few-pixels``.
        reason: why ``scale`` is NaN (``""`` when it is not).
    """

    scale: float
    medians: np.ndarray
    n_valid_pixels: np.ndarray
    n_used: int
    skipped: list[tuple[int, str]] = field(default_factory=list)
    reason: str = ""

    @property
    def ok(self) -> bool:
        return bool(np.isfinite(self.scale) and self.scale > 0)


def resize_nearest(a: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
    """Nearest-neighbour resample of a 2-D array to ``shape`` on pixel centres.

    Output pixel ``(r, c)`` takes input pixel ``(floor((r + 0.5) * H_in / H_out),
    floor((c + 0.5) * W_in / W_out))``; identity when shapes agree.
    """
    if a.shape == tuple(shape):
        return a
    h_in, w_in = a.shape
    h, w = shape
    rows = np.minimum(((np.arange(h) + 0.5) * h_in / h).astype(np.int64), h_in - 1)
    cols = np.minimum(((np.arange(w) + 0.5) * w_in / w).astype(np.int64), w_in - 1)
    return a[rows[:, None], cols[None, :]]


def _as_2d(a: np.ndarray, name: str) -> np.ndarray:
    arr = np.asarray(a, dtype=np.float64)
    if arr.ndim != 2 or arr.size == 0:
        raise ScaleError(f"{name}: expected a non-empty 2-D depth map, got shape {arr.shape}")
    return arr


def recover_scale(
    metric_depths_m: Sequence[np.ndarray | None],
    backbone_depths: Sequence[np.ndarray | None],
    confidences: Sequence[np.ndarray | None] | None = None,
    min_pixels: int = DEFAULT_MIN_PIXELS,
) -> ScaleEstimate:
    """Mean over keyframes of the per-keyframe median ratio ``Dstar / D``.

    Args:
        metric_depths_m: ``K`` metric references ``[H*,W*]`` in metres (0 / NaN =
            unknown), None where a keyframe has none.
        backbone_depths: ``K`` backbone depths ``[H,W]`` (any positive unit), None
            where the backbone gave none (e.g. an invalid view).
        confidences: optional ``K`` maps ``[H,W]`` (>= 0); pixels with confidence 0
            are invalid.
        min_pixels: keyframes with fewer valid pixels are skipped.

    Raises:
        ScaleError: list lengths differ, a map is not 2-D, or a confidence map's
            shape differs from its backbone depth's.
    """
    K = len(backbone_depths)
    if len(metric_depths_m) != K:
        raise ScaleError(f"recover_scale: {len(metric_depths_m)} metric depths for {K} backbone depths")
    if confidences is not None and len(confidences) != K:
        raise ScaleError(f"recover_scale: {len(confidences)} confidence maps for {K} backbone depths")
    if min_pixels < 1:
        raise ScaleError(f"recover_scale: min_pixels must be >= 1, got {min_pixels}")
    medians = np.full(K, np.nan)
    counts = np.zeros(K, dtype=np.int64)
    skipped: list[tuple[int, str]] = []
    for k in range(K):
        if backbone_depths[k] is None:
            skipped.append((k, "no-backbone-depth"))
            continue
        D = _as_2d(backbone_depths[k], f"backbone_depths[{k}]")
        if metric_depths_m[k] is None:
            skipped.append((k, "no-metric-depth"))
            continue
        Dstar = resize_nearest(_as_2d(metric_depths_m[k], f"metric_depths_m[{k}]"), D.shape)
        with np.errstate(invalid="ignore"):
            valid = np.isfinite(D) & (D > 0) & np.isfinite(Dstar) & (Dstar > 0)
        if confidences is not None and confidences[k] is not None:
            C = _as_2d(confidences[k], f"confidences[{k}]")
            if C.shape != D.shape:
                raise ScaleError(f"confidences[{k}]: shape {C.shape} differs from backbone_depths[{k}] {D.shape}")
            with np.errstate(invalid="ignore"):
                valid &= np.isfinite(C) & (C > 0)
        counts[k] = int(valid.sum())
        if counts[k] < min_pixels:
            skipped.append((k, "too-few-pixels"))
            continue
        medians[k] = float(np.median(Dstar[valid] / D[valid]))
    used = np.isfinite(medians)
    n_used = int(used.sum())
    if n_used == 0:
        reason = "no keyframes" if K == 0 else "no keyframe with enough valid pixels: " + ", ".join(
            f"#{k} {r}" for k, r in skipped)
        return ScaleEstimate(float("nan"), medians, counts, 0, skipped, reason)
    return ScaleEstimate(float(np.mean(medians[used])), medians, counts, n_used, skipped)


# --------------------------------------------------------------------------- step length
@dataclass(frozen=True)
class StepLengthRule:
    """When a metric ego-motion step is too slow after the motion before it to be believed.

    A pass can place the current view on the wrong motion. A vehicle ahead that holds
    most keypoints and surface, moving with the camera, makes a fast car measure a
    fraction of its speed for as long as it stays in view. The scale looks collapsed
    although every depth is right. Kinematics bound how fast a platform slows down.

    The reference speed is the median of the last ``window`` accepted steps' speeds, once
    there are ``min_history`` and they are steady. A step's speed ``|t| / dt`` is implausible
    when it is below the reference by more than a factor ``max_ratio``. It must also be below
    by more than ``max_accel_mps2`` times the time since the last accepted step, plus
    ``noise_m / dt``. That last term is the position noise of one step, so slow platforms and
    short steps never trip the rule. The bound widens with every held step: a slower speed
    that persists is accepted once the platform could have braked to it.

    Only drops are held. The failure is a collapse (a co-moving object, the at-rest motion
    prior of a sequence's first steps); a rise after collapsed steps is the odometry
    recovering, and a median reference is not moved by a single fast step. ``max_accel_mps2
    = 0`` switches the rule off.
    """

    max_ratio: float = 2.0
    max_accel_mps2: float = 5.0
    noise_m: float = 0.05
    window: int = 5
    min_history: int = 3

    def __post_init__(self) -> None:
        if not (np.isfinite(self.max_ratio) and self.max_ratio > 1.0):
            raise ScaleError(f"StepLengthRule: max_ratio must be > 1, got {self.max_ratio}")
        for name in ("max_accel_mps2", "noise_m"):
            v = getattr(self, name)
            if not (np.isfinite(v) and v >= 0):
                raise ScaleError(f"StepLengthRule: {name} must be finite and >= 0, got {v}")
        if int(self.window) < 1 or not (1 <= int(self.min_history) <= int(self.window)):
            raise ScaleError(f"StepLengthRule: need 1 <= min_history <= window, got {self.min_history}, {self.window}")

    @property
    def enabled(self) -> bool:
        return self.max_accel_mps2 > 0

    def reference(self, speeds_mps: Sequence[float]) -> float | None:
        """The reference speed of the accepted speeds so far (oldest first): their median over the
        last ``window``; None when there are fewer than ``min_history`` or they are not steady
        (fastest more than ``max_ratio`` times the slowest: no speed to hold)."""
        if len(speeds_mps) < int(self.min_history):
            return None
        v = np.asarray(speeds_mps, np.float64)[-int(self.window):]
        if v.max() > self.max_ratio * v.min():
            return None
        return float(np.median(v))

    def plausible(self, length_m: float, dt_s: float, ref_speed_mps: float | None, since_ref_s: float) -> bool:
        """Whether a step of ``length_m`` over ``dt_s`` seconds is believable after a reference
        speed ``ref_speed_mps`` (None: nothing to compare with) whose last step ended
        ``since_ref_s`` seconds ago."""
        if not self.enabled or ref_speed_mps is None or not (np.isfinite(length_m) and dt_s > 0):
            return True
        speed = length_m / dt_s
        ref = float(ref_speed_mps)
        if speed * self.max_ratio >= ref:
            return True
        return ref - speed <= self.max_accel_mps2 * max(since_ref_s, dt_s) + self.noise_m / dt_s


def step_ratios(lengths_m: np.ndarray, true_lengths_m: np.ndarray, min_true_m: float = 0.0) -> dict[str, float]:
    """Figures of predicted / true step length over the steps whose true length is at least
    ``min_true_m``: ``n``, ``median``, ``p10``, ``p90``, ``outside`` (ratios outside [0.5, 2])."""
    L = np.asarray(lengths_m, np.float64)
    G = np.asarray(true_lengths_m, np.float64)
    ok = np.isfinite(L) & np.isfinite(G) & (G > 0) & (G >= min_true_m)
    r = L[ok] / G[ok]
    if len(r) == 0:
        return {"n": 0, "median": float("nan"), "p10": float("nan"), "p90": float("nan"), "outside": 0}
    return {"n": int(len(r)), "median": float(np.median(r)), "p10": float(np.quantile(r, 0.1)),
            "p90": float(np.quantile(r, 0.9)), "outside": int(np.count_nonzero((r < 0.5) | (r > 2.0)))}

"""Simulated metric depth sources (:class:`cerpe.protocols.MetricDepthSource`).

Both read the exact depth from ``FrameContext.sensor_depth_m`` (the synthetic
renderer's) and degrade it in a documented, seeded way; both are *simulations*
and say so in their names. Output is ``[H,W] float32`` metres, 0 = unknown.
Randomness is a function of ``(seed, robot_id, step)`` only, so a rerun gives
identical depth. The depth sources (:mod:`cerpe.backbones.depth`) build them by
name; the synthetic generator (:mod:`cerpe.synth`) names their options in the
manifests it writes. This module knows neither.
"""
from __future__ import annotations

import zlib
from dataclasses import dataclass
from typing import ClassVar

import cv2
import numpy as np

from .errors import CerpeError
from .protocols import FrameContext, View


class DepthSimError(CerpeError, ValueError):
    """A frame whose exact depth a simulation cannot use (the message names robot and step)."""


def _rng(seed: int, robot_id: str, step: int, salt: int) -> np.random.Generator:
    return np.random.default_rng([int(seed) & 0xFFFFFFFF, zlib.crc32(str(robot_id).encode()), int(step), salt])


def _exact(frame: FrameContext, who: str) -> np.ndarray | None:
    d = frame.sensor_depth_m
    if d is None:
        return None
    d = np.asarray(d, np.float32)
    if d.ndim != 2:
        raise DepthSimError(f"{who}: FrameContext.sensor_depth_m of robot {frame.robot_id} step {frame.step} "
                         f"must be [H,W], got shape {d.shape}")
    return np.where(np.isfinite(d) & (d > 0), d, 0.0).astype(np.float32)


_CV_MIN_SIDE = 8  # the smallest side (px) of a map depth_edges hands to OpenCV


def depth_edges(depth_m: np.ndarray, rel_jump: float = 0.05, dilate_px: int = 1) -> np.ndarray:
    """``[H,W] bool``: pixels next to a depth discontinuity (relative jump > ``rel_jump``),
    or next to no-surface pixels, dilated by ``dilate_px``."""
    d = np.ascontiguousarray(depth_m, np.float32)
    edge = np.zeros(d.shape, np.uint8)
    # the test is symmetric in the two pixels of a pair: each horizontal and vertical pair once,
    # marking both of its pixels (a pixel past the border is the pixel itself: never an edge)
    for a, b, mark_a, mark_b in ((d[:, :-1], d[:, 1:], edge[:, :-1], edge[:, 1:]),
                                 (d[:-1, :], d[1:, :], edge[:-1, :], edge[1:, :])):
        jump = _jumps(a, b, rel_jump)
        mark_a |= jump
        mark_b |= jump
    if dilate_px > 0 and edge.size:
        edge = cv2.dilate(edge, np.ones((2 * dilate_px + 1,) * 2, np.uint8))
    return edge.astype(bool)


def _jumps(a: np.ndarray, b: np.ndarray, rel_jump: float) -> np.ndarray:
    """``[h,w] uint8``, nonzero where ``|b - a| > rel_jump * max(min(a, b), 1e-3)`` or only one of the two
    is positive (float32 arithmetic). Maps of at least :data:`_CV_MIN_SIDE` pixels a side go through
    OpenCV's element-wise functions: the same float32 operations as numpy's, without its temporaries,
    twice as fast at 640x480. Smaller ones stay in numpy: OpenCV takes no empty array and may read an
    array of four values or fewer as a scalar."""
    jump_tol, floor = np.float32(rel_jump), np.float32(1e-3)
    if min(a.shape) < _CV_MIN_SIDE:
        jump = (np.abs(b - a) > jump_tol * np.maximum(np.minimum(a, b), floor)) | ((a > 0) != (b > 0))
        return jump.astype(np.uint8)
    tol = cv2.max(cv2.min(a, b), float(floor))
    tol *= jump_tol
    jump = cv2.compare(cv2.absdiff(a, b), tol, cv2.CMP_GT)
    jump |= cv2.compare((a > 0).view(np.uint8), (b > 0).view(np.uint8), cv2.CMP_NE)
    return jump


def upper_quantile(values: np.ndarray, q: float) -> float:
    """``np.quantile(values, q)`` (linear interpolation), bit for bit, for ``q`` near 1 in a large array.

    The two order statistics it interpolates lie in the top ``n (1 - q)`` values, so only the values
    above a bound taken from a strided sample are partitioned (a quarter of the time at 640x480);
    the interpolation itself is numpy's, on those two values. When the bound keeps too few values
    it is ``np.quantile`` on all of them. ``values`` must be finite (a NaN would be ranked apart from
    where numpy ranks it), as the simulation's random fields are."""
    a = np.asarray(values).reshape(-1)
    n = a.size
    k = int(np.floor((n - 1) * np.float64(q)))  # numpy's lower index, (n - 1) q floored
    top = n - k  # values at or above the lower order statistic
    if n < 4096 or top < 2 or top > n // 8:  # small, the largest value, or not near 1
        return float(np.quantile(a, q))
    sample = a[::16]
    j = max(len(sample) - 2 * (top // 16) - 16, 0)  # about twice the values needed above the bound
    bound = np.partition(sample, j)[j]
    cand = a[a >= bound]
    if len(cand) < top:
        return float(np.quantile(a, q))
    kc = k - (n - len(cand))  # every value left out is below every candidate
    cand.partition((kc, kc + 1))
    gamma = float((n - 1) * np.float64(q) - k)
    return float(np.quantile(np.array([cand[kc], cand[kc + 1]], a.dtype), gamma))


@dataclass
class SensorDepthSim:
    """An RGB-D / stereo depth *sensor simulation* (name ``"sensor"``).

    Model (z = exact depth in metres):
      * range: only ``min_m <= z <= max_m`` is measured (defaults 0.3..10 m, an
        indoor structured-light sensor; use e.g. 0.5..40 m for outdoor stereo);
      * noise: ``z + N(0, (sigma_at_1m * z^2)^2)`` (error grows with z^2, 1.5 mm at 1 m);
      * missing edges: pixels within ``edge_px`` of a depth discontinuity are dropped;
      * dropouts: a fraction ``dropout`` of pixels at random, plus blob holes
        (smooth random field above a threshold) covering about ``hole_fraction``.
    """

    min_m: float = 0.3
    max_m: float = 10.0
    sigma_at_1m: float = 0.0015
    dropout: float = 0.02
    hole_fraction: float = 0.03
    edge_px: int = 1
    seed: int = 0
    name: str = "sensor"
    sensor: ClassVar[bool] = True  # a sensor's depth comes with the frame: simulating it is not the robot's work

    @classmethod
    def outdoor(cls, **kw) -> "SensorDepthSim":
        """An outdoor stereo-like range: 0.5..40 m (other fields as given)."""
        return cls(**{**OUTDOOR_SENSOR, **kw})

    @property
    def rel_sigma(self) -> float:
        """Relative sigma of the depth map's scale (:class:`~cerpe.protocols.MetricDepthSource`): none,
        the simulated sensor's errors are per pixel (they average out over a placement's points)."""
        return 0.0

    def depth_m(self, view: View, frame: FrameContext) -> np.ndarray | None:
        z = _exact(frame, "SensorDepthSim")
        if z is None:
            return None
        rng = _rng(self.seed ^ frame.seed, frame.robot_id, frame.step, 1)
        H, W = z.shape
        # z + N(0,1) * (sigma z^2), in float32, in place (the same operations, fewer temporaries)
        out = z * np.float32(self.sigma_at_1m)
        out *= z
        out *= rng.standard_normal(z.shape).astype(np.float32)
        out += z
        keep = (z >= np.float32(self.min_m)) & (z <= np.float32(self.max_m))
        keep &= rng.random(z.shape) >= self.dropout
        if self.hole_fraction > 0:
            field = cv2.resize(rng.standard_normal((max(H // 24, 2), max(W // 24, 2))).astype(np.float32), (W, H),
                               interpolation=cv2.INTER_CUBIC)
            keep &= field < upper_quantile(field, 1.0 - self.hole_fraction)
        if self.edge_px > 0:
            keep &= ~depth_edges(z, dilate_px=self.edge_px)
        np.copyto(out, np.float32(0.0), where=~keep)
        return out


@dataclass
class MonoDepthSim:
    """A *simulation* of a monocular metric-depth network's errors (name ``"mono-sim"``).

    It stands in for Metric3Dv2 only because that network's weights cannot be
    obtained here; the real adapter lives in ``cerpe.backbones.metric3d``.
    Error model applied to the exact depth z (all factors multiplicative):
      * per-frame global scale bias ``exp(N(0, scale_sigma))`` (default 0.08, i.e. ~8 %);
      * smooth low-frequency distortion ``exp(g)`` with ``g`` a random field on a
        ``grid`` (4x3) of N(0, distortion_sigma=0.05) values, bicubically upsampled;
      * pixel noise ``exp(N(0, noise_sigma=0.01))``;
      * depth edges (within ``edge_px`` px) are blurred across the boundary by a
        ``edge_blur_px`` box filter and get extra noise ``N(0, edge_sigma=0.1)``
        (relative), like a network's smeared object boundaries;
      * output clamped to ``[0, max_m=300]``; pixels with no surface stay 0.
    """

    scale_sigma: float = 0.08
    distortion_sigma: float = 0.05
    grid: tuple[int, int] = (4, 3)
    noise_sigma: float = 0.01
    edge_px: int = 2
    edge_blur_px: int = 5
    edge_sigma: float = 0.1
    max_m: float = 300.0
    seed: int = 0
    name: str = "mono-sim"

    @property
    def rel_sigma(self) -> float:
        """Relative sigma of the depth map's scale (:class:`~cerpe.protocols.MetricDepthSource`): the
        per-frame scale bias and the low-frequency distortion, which a placement's points share."""
        return float(np.hypot(self.scale_sigma, self.distortion_sigma))

    def depth_m(self, view: View, frame: FrameContext) -> np.ndarray | None:
        z = _exact(frame, "MonoDepthSim")
        if z is None:
            return None
        rng = _rng(self.seed ^ frame.seed, frame.robot_id, frame.step, 2)
        H, W = z.shape
        scale = float(np.exp(rng.normal(0.0, self.scale_sigma)))
        g = rng.normal(0.0, self.distortion_sigma, (self.grid[1], self.grid[0])).astype(np.float32)
        field = cv2.resize(g, (W, H), interpolation=cv2.INTER_CUBIC)
        noise = rng.normal(0.0, self.noise_sigma, z.shape).astype(np.float32)
        out = z * scale * np.exp(field + noise)
        edges = depth_edges(z, dilate_px=self.edge_px) & (z > 0)
        if edges.any():
            k = max(int(self.edge_blur_px), 1)
            valid = (z > 0).astype(np.float32)
            blur = cv2.blur(out * valid, (k, k)) / np.maximum(cv2.blur(valid, (k, k)), 1e-6)
            out = np.where(edges, blur * (1.0 + rng.normal(0.0, self.edge_sigma, z.shape)).astype(np.float32), out)
        out = np.clip(out, 0.0, self.max_m)
        return np.where(z > 0, out, 0.0).astype(np.float32)


# An outdoor stereo-like range (``SensorDepthSim.outdoor``).
OUTDOOR_SENSOR: dict[str, float] = {"min_m": 0.5, "max_m": 40.0}

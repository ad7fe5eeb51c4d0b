"""Metric depth sources behind :class:`cerpe.protocols.MetricDepthSource`, by name.

``build_depth_source(name, conf)`` with ``name`` one of :data:`DEPTH_SOURCES`:

* ``sensor``   -- simulated RGB-D sensor over the renderer's exact depth
  (:class:`cerpe.depthsim.SensorDepthSim`: noise, range limits, holes);
* ``mono-sim`` -- simulated monocular metric-depth network
  (:class:`cerpe.depthsim.MonoDepthSim`: global scale bias and structured error),
  the stand-in for Metric3Dv2 on synthetic data;
* ``dataset``  -- the dataset's own metric depth, :attr:`FrameContext.sensor_depth_m`
  (RGB-D images, LiDAR projected into the camera by the adapter);
* ``metric3d`` -- Metric3Dv2 from user-supplied weights (:mod:`cerpe.backbones.metric3d`);
* ``none``     -- no metric depth (scale stays unknown; the algorithm counts it).

Heavy or optional modules are imported only when their source is built.
"""
from __future__ import annotations

import dataclasses
from typing import Any, Sequence

import numpy as np

from ..depthsim import MonoDepthSim, SensorDepthSim
from ..protocols import BackboneError, FrameContext, View

DEPTH_SOURCES: tuple[str, ...] = ("sensor", "mono-sim", "dataset", "metric3d", "none")
# relative scale sigma of a dataset's own depth (RGB-D sensors, projected LiDAR): about 1 %, an assumption
# (a depth camera's scale calibration), overridden by the manifest's metric_depth_options {rel_sigma: ...}
DATASET_REL_SIGMA = 0.01


class DepthSourceError(BackboneError):
    """Unknown depth source name or a depth source that cannot be built."""


class DatasetDepth:
    """Returns the dataset's metric depth for the frame (``FrameContext.sensor_depth_m``).

    Non-finite and non-positive values become 0 (unknown); a map whose size
    differs from the image raises :class:`DepthSourceError` naming robot and step.
    ``rel_sigma`` (option, default :data:`DATASET_REL_SIGMA`): the relative sigma of the
    depth's scale (:class:`~cerpe.protocols.MetricDepthSource`).
    """

    name = "dataset"
    sensor = True  # recorded with the frame: reading it is not the robot's work

    def __init__(self, conf: dict[str, Any] | None = None) -> None:
        self.conf = _known_options(conf, ("rel_sigma",), self.name)
        r = self.conf.get("rel_sigma", DATASET_REL_SIGMA)
        if not isinstance(r, (int, float)) or not np.isfinite(r) or r < 0:
            raise DepthSourceError(f"depth source 'dataset': rel_sigma must be a finite number >= 0, got {r!r}")
        self.rel_sigma = float(r)

    def depth_m(self, view: View, frame: FrameContext) -> np.ndarray | None:
        d = frame.sensor_depth_m
        if d is None:
            return None
        d = np.asarray(d, dtype=np.float32)
        if d.ndim != 2 or d.shape != view.image.shape[:2]:
            raise DepthSourceError(
                f"dataset depth of robot {frame.robot_id} step {frame.step}: shape {d.shape} "
                f"does not match the image {view.image.shape[:2]}")
        return np.where(np.isfinite(d) & (d > 0), d, 0.0).astype(np.float32)


class NoDepth:
    """No metric depth at all: every frame returns None (``metric`` False: the algorithm then uses s = 1 and
    such runs are evaluated at ground-truth scale only)."""

    name = "none"
    metric = False

    def __init__(self, conf: dict[str, Any] | None = None) -> None:
        self.conf = _known_options(conf, (), self.name)

    def depth_m(self, view: View, frame: FrameContext) -> np.ndarray | None:
        return None


def _known_options(conf: dict[str, Any] | None, known: Sequence[str], what: str) -> dict[str, Any]:
    """``conf`` as a dict; DepthSourceError naming the unknown options and the known ones (a
    misspelt option would otherwise be ignored without a word)."""
    conf = dict(conf or {})
    unknown = sorted(set(conf) - set(known))
    if unknown:
        raise DepthSourceError(f"depth source {what!r}: bad options {sorted(conf)}: unknown option(s) {unknown}; "
                               f"known: {list(known) or 'none'}")
    return conf


def _simulation(cls: type, conf: dict[str, Any], what: str) -> Any:
    """A depth simulation (a dataclass) from the manifest's ``metric_depth_options``."""
    _known_options(conf, [f.name for f in dataclasses.fields(cls) if f.name != "name"], what)
    try:
        return cls(**conf)
    except (TypeError, ValueError) as exc:
        raise DepthSourceError(f"depth source {what!r}: bad options {sorted(conf)}: {exc}") from None


def build_depth_source(name: str, conf: dict[str, Any] | None = None) -> Any:
    """Build the metric depth source called ``name`` (see the module docstring).

    Raises:
        DepthSourceError: for an unknown name (listing the valid ones) or a
            source whose module is missing.
    """
    conf = dict(conf or {})
    if name == "dataset":
        return DatasetDepth(conf)
    if name == "none":
        return NoDepth(conf)
    if name == "sensor":
        return _simulation(SensorDepthSim, conf, name)
    if name == "mono-sim":
        return _simulation(MonoDepthSim, conf, name)
    if name == "metric3d":
        try:
            from .metric3d import Metric3DDepth  # heavy and optional: only when asked for
        except ModuleNotFoundError as exc:
            raise DepthSourceError(f"depth source {name!r}: {exc}") from None
        try:
            return Metric3DDepth(conf) if conf else Metric3DDepth()
        except TypeError as exc:
            raise DepthSourceError(f"depth source {name!r}: bad options {sorted(conf)}: {exc}") from None
    raise DepthSourceError(f"unknown depth source {name!r}; valid: {', '.join(DEPTH_SOURCES)}")

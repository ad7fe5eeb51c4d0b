"""A :class:`~cerpe.backbones.config.BackboneConfig` -> the three plug-ins (descriptor, pose backbone, metric depth).

``models: offline`` (the default; what ``make paper`` and every test use): XFeat +
the training-free SALAD-style descriptor (:mod:`cerpe.backbones.descriptor`) +
the classical multi-view geometry backbone (:mod:`cerpe.backbones.offline`);
descriptor and backbone share one XFeat encoder and cache, so each image is
encoded once. ``models: paper``: VGGT + SALAD/DINOv2 + Metric3Dv2 from user-supplied
weights, built lazily by :func:`cerpe.backbones.paper_profile.build_paper`.

The depth source is chosen separately (it depends on the data, see
:mod:`cerpe.backbones.depth`), e.g. from the manifest's ``metric_depth``.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Any

from .config import BackboneConfig

# the offline plug-ins' depth source when none is given: the simulated RGB-D sensor
OFFLINE_DEPTH = "sensor"


@dataclass
class Plugins:
    """The plug-ins of one robot (or of a team sharing them)."""

    descriptor: Any
    backbone: Any
    depth: Any
    models: str = "offline"


def build_plugins(conf: BackboneConfig | None = None, depth: str | None = None,
                  depth_options: dict | None = None) -> Plugins:
    """Build the plug-ins of ``conf.models`` with ``conf``'s settings.

    Args:
        conf: the backbone configuration (None: the defaults, ``models: offline``).
        depth: depth source name (:data:`cerpe.backbones.depth.DEPTH_SOURCES`; None: ``sensor``
            for the offline models, ``metric3d`` for the paper's).
        depth_options: the depth source's options (manifest ``metric_depth_options``).
    """
    conf = conf or BackboneConfig()
    if conf.models == "paper":
        from . import paper_profile  # lazy: needs user weights and optional packages

        descriptor, backbone, depth_src = paper_profile.build_paper(conf.paper, depth, depth_options)
        return Plugins(descriptor, backbone, depth_src, models="paper")
    from .depth import build_depth_source
    from .descriptor import XFeatSaladDescriptor
    from .offline import OfflineGeometryBackbone
    from .xfeat import shared_encoder

    off = conf.offline
    encoder = shared_encoder(off.keypoints, precision=off.precision)
    descriptor = XFeatSaladDescriptor(off.descriptor, encoder=encoder)
    backbone = OfflineGeometryBackbone(off, encoder=encoder)
    return Plugins(descriptor, backbone, build_depth_source(depth or OFFLINE_DEPTH, depth_options), models="offline")


def descriptor_thresholds(conf: BackboneConfig | None = None) -> dict[str, float]:
    """The gate and keyframe thresholds (``tau``, ``tau_m``, ``tau_k``) of ``conf.models``' descriptor,
    without building it: the offline descriptor's calibration file, the paper's values for SALAD."""
    conf = conf or BackboneConfig()
    if conf.models == "paper":
        from .paper_profile import PAPER_PARAMETERS

        return {k: float(PAPER_PARAMETERS[k]) for k in ("tau", "tau_m", "tau_k")}
    from .descriptor import default_thresholds

    return dict(default_thresholds())

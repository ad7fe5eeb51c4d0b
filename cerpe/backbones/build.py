"""Named presets -> the three plug-ins (descriptor, pose backbone, metric depth).

``offline`` (the default; what ``make paper`` and every test use): XFeat +
the training-free SALAD-style descriptor (:mod:`cerpe.backbones.descriptor`) +
the classical multi-view geometry backbone (:mod:`cerpe.backbones.offline`);
descriptor and backbone share one XFeat encoder and cache, so each image is
encoded once. ``paper``: VGGT + SALAD/DINOv2 + Metric3Dv2 from user-supplied
weights, built lazily by :func:`cerpe.backbones.paper_profile.build_paper`.

The depth source is chosen separately (it depends on the data, see
:mod:`cerpe.backbones.depth`), e.g. from the manifest's ``metric_depth``.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Any

from ..config import merge_conf
from ..protocols import BackboneError
from .xfeat import XFeatEncoder

PRESETS: dict[str, dict[str, Any] | None] = {
    "offline": {
        # 1024 keypoints: `cerpe bench --all-encounters` shows the latency/accuracy trade-off against 2048;
        # the descriptor aggregates the best 1024 either way.
        "xfeat": {**XFeatEncoder.default_conf, "top_k": 1024, "detection_threshold": 0.05},
        "descriptor": {},  # XFeatSaladDescriptor conf, checked there
        "backbone": {},  # OfflineGeometryBackbone conf, checked there
        "depth": "sensor",
        "depth_conf": {},
    },
    "paper": None,  # the conf goes whole to paper_profile.build_paper, checked against its default_conf
}


class BuildError(BackboneError):
    """Unknown preset or a preset that cannot be built."""


@dataclass
class Plugins:
    """The plug-ins of one robot (or of a team sharing them)."""

    descriptor: Any
    backbone: Any
    depth: Any
    preset: str = "offline"


def build_plugins(preset: Any = "offline", conf: dict[str, Any] | None = None,
                  depth: str | None = None, depth_options: dict | None = None) -> Plugins:
    """Build the plug-ins of ``preset`` with ``conf`` overrides (nested dicts merge deeply).

    Args:
        preset: ``offline`` or ``paper``.
        conf: overrides of the preset (keys ``xfeat``, ``descriptor``, ``backbone``,
            ``depth``, ``depth_conf``; the ``paper`` preset passes it on whole to
            :func:`cerpe.backbones.paper_profile.build_paper`). Merged strictly
            (:func:`cerpe.config.merge_conf`): an unknown key is refused.
        depth: depth source name; overrides ``conf["depth"]``.

    Raises:
        BuildError: unknown preset (listing the valid ones).
    """
    if not isinstance(preset, str):  # TEMPORARY shim until the backbone tree lands: a BackboneConfig
        preset = preset.models
        conf = {"depth_conf": dict(depth_options or {})}
    if preset not in PRESETS:
        raise BuildError(f"unknown backbone preset {preset!r}; valid: {', '.join(PRESETS)}")
    defaults = PRESETS[preset]
    full = dict(conf or {}) if defaults is None else merge_conf(defaults, conf, f"preset {preset!r} conf")
    if depth is not None:
        full["depth"] = depth
    if preset == "paper":
        from . import paper_profile  # lazy: needs user weights and optional packages

        built = paper_profile.build_paper(full)
        if isinstance(built, Plugins):
            return built
        descriptor, backbone, depth_src = built
        return Plugins(descriptor, backbone, depth_src, preset="paper")
    from .depth import build_depth_source
    from .descriptor import XFeatSaladDescriptor
    from .offline import OfflineGeometryBackbone
    from .xfeat import shared_encoder

    encoder = shared_encoder(full["xfeat"])
    descriptor = XFeatSaladDescriptor({**full["descriptor"], "xfeat": full["xfeat"]}, encoder=encoder)
    backbone = OfflineGeometryBackbone({**full["backbone"], "xfeat": full["xfeat"]}, encoder=encoder)
    return Plugins(descriptor, backbone, build_depth_source(full["depth"], full["depth_conf"]), preset=preset)

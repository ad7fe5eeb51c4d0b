"""The method's whole configuration: one tree grouped by phase, and its named presets.

:class:`CerpeConfig` is Algorithm 1's groups (:class:`cerpe.algorithm.config.AlgorithmConfig`: gate,
memory, scale, odometry, anchors, policy, backend, messages) plus ``backbone``, the plug-ins and their
knobs (:class:`cerpe.backbones.config.BackboneConfig`). Every leaf is a :func:`cerpe.knobs.knob` with its
meaning and unit; ``cerpe config show`` prints the tree and ``docs/config.md`` is generated from it.

A preset is a named set of dotted overrides of the defaults, as hloc names its configurations. The
defaults are the paper's protocol (the CERPE row of Table I); the CERPE methods of ``cerpe run`` add
their own override on top (``cerpe-wo-em``: no propagation; ``cerpe-graph``: the pose graph):
:func:`build` resolves ``preset -> method -> --set`` in that order.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Mapping, Sequence

from . import knobs
from .algorithm.config import AlgorithmConfig
from .backbones.config import BackboneConfig
from .errors import CerpeError
from .knobs import KnobError, group

__all__ = ["CerpeConfig", "PRESETS", "PRESET_NOTES", "METHOD_OVERRIDES", "ConfigError", "build", "parse_sets",
           "preset_overrides"]


class ConfigError(CerpeError, ValueError):
    """An unknown preset or key, or a value of the wrong type (one line naming it and the known ones)."""


@dataclass(frozen=True)
class CerpeConfig(AlgorithmConfig):
    """The method's whole configuration (see the module docstring)."""

    backbone: BackboneConfig = group(BackboneConfig, "the plug-ins: descriptor, pose backbone and their knobs")


# Smaller messages (ours): the int8 descriptor codec and WebP-75 full-resolution replies.
_COMPRESSED: dict[str, Any] = {"messages.descriptor_codec": "pca-int8", "messages.reply_codec": "webp",
                               "messages.reply_quality": 75}

#: name -> dotted overrides of the defaults (the paper's protocol).
PRESETS: dict[str, dict[str, Any]] = {
    "paper": {},
    "graph": {"backend.kind": "graph"},
    "always": {"policy.mode": "always"},
    "pays": {"policy.mode": "pays"},
    "pays-compressed": {"policy.mode": "pays", **_COMPRESSED},
    "lean": {"policy.mode": "pays", "policy.miss_limit": 3, "policy.miss_backoff_steps": 3,
             "policy.unanchored_backoff_steps": 2, "policy.backoff_pending_exempt": True,
             "policy.recheck_rot_rad": 0.03, "policy.recheck_limit": 1, **_COMPRESSED,
             "messages.reply_codec": "webp-grey"},
    "share": {"messages.share_estimates": True},
    "robot": {"backbone.offline.precision": "auto"},
}
#: name -> one line: what the preset is for.
PRESET_NOTES: dict[str, str] = {
    "paper": "the paper's protocol: request an image whenever the gate opens, switch back end (Table I's CERPE)",
    "graph": "ours: the paper's messages, a robust pose graph per pair instead of the switch (with covariances)",
    "always": "reference: an image to every peer at every step, gate or not",
    "pays": "ours: request an image only when it pays (no fresh, certain anchor)",
    "pays-compressed": "ours: pays, with the int8 descriptor codec and WebP-75 replies",
    "lean": "ours at its leanest: pays + back-off from gates whose images place nothing + one recheck, "
            "compressed descriptor, grey WebP-75 replies",
    "share": "ours: robots also share their direct estimates (62 B each)",
    "robot": "the paper's protocol at a robot's speed: XFeat's deeper convolutions in bfloat16 where the CPU "
             "has it natively (the tables use fp32)",
}
#: method -> what it sets on top of the preset.
METHOD_OVERRIDES: dict[str, dict[str, Any]] = {
    "cerpe": {},
    "cerpe-wo-em": {"backend.propagate": False},
    "cerpe-graph": {"backend.kind": "graph"},
}


def preset_overrides(preset: str) -> dict[str, Any]:
    """The dotted overrides of ``preset``; :class:`ConfigError` listing the known presets."""
    if preset not in PRESETS:
        raise ConfigError(f"unknown preset {preset!r}; known: {', '.join(PRESETS)}")
    return dict(PRESETS[preset])


def build(preset: str = "paper", method: str = "cerpe", sets: Mapping[str, Any] | None = None) -> CerpeConfig:
    """The tree of ``preset``, then ``method``'s override, then ``sets`` (dotted keys or nested dicts).

    Raises :class:`ConfigError` (one line naming the key, preset or method and the known ones).
    """
    if method not in METHOD_OVERRIDES:
        raise ConfigError(f"method {method!r} has no configuration tree; cerpe methods: {', '.join(METHOD_OVERRIDES)}")
    tree = CerpeConfig()
    try:
        for what in (preset_overrides(preset), METHOD_OVERRIDES[method], dict(sets or {})):
            tree = knobs.override(tree, what)
    except KnobError as exc:
        raise ConfigError(str(exc)) from None
    return tree


def parse_sets(items: Sequence[str]) -> dict[str, Any]:
    """``--set KEY=VALUE`` arguments -> ``{"dotted.key": value}`` (values parsed as YAML; the last of a key wins).

    The keys are checked against the tree by :func:`build`.
    """
    import yaml

    out: dict[str, Any] = {}
    for item in items:
        key, sep, raw = str(item).partition("=")
        parts = [k.strip() for k in key.split(".")]
        if not sep or not all(parts):
            raise ConfigError(f"--set {item!r}: expected KEY=VALUE with a dotted key, e.g. policy.mode=pays")
        try:
            value = yaml.safe_load(raw)
        except yaml.YAMLError as exc:
            raise ConfigError(f"--set {item!r}: the value is not YAML ({str(exc).splitlines()[0]})") from None
        out[".".join(parts)] = value
    return out

"""PLACEHOLDER (replaced by the backbone-tree branch): the backbone group of the configuration tree."""
from __future__ import annotations

from dataclasses import dataclass

from ..knobs import Group, knob

MODELS: tuple[str, ...] = ("offline", "paper")


@dataclass(frozen=True)
class BackboneConfig(Group):
    """The plug-ins: which models, and their knobs."""

    models: str = knob("offline", "offline: the stand-ins that run here; paper: VGGT + SALAD/DINOv2 + Metric3Dv2 "
                       "from your weights", choices=MODELS)

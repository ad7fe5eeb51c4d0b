"""Synthetic encounter worlds: a numpy CPU renderer, two seeded world generators
(``cad-intersection``, ``indoor-team``) and the writer behind ``cerpe synth``
(mocap-style dataset with manifest). The simulated depth sources the written
manifests name live in :mod:`cerpe.depthsim`.

Public API (imported lazily so ``import cerpe.synth`` stays cheap)::

    generate_suite(world, out_dir, conf) -> manifest path
    generate_suites(name, out_root) -> {setting: manifest path}     # SUITES: fixture, paper-default
    render_encounter(world, seed, index, conf) -> cerpe.scene.Encounter   (in memory)
    sensor_options(world) -> SensorDepthSim options that suit the world
"""
from __future__ import annotations

from .errors import SynthError

__all__ = ["SynthError", "generate_suite", "generate_suites", "render_encounter", "sensor_options", "SUITES",
           "WORLDS"]


def __getattr__(name: str):
    if name in ("generate_suite", "generate_suites", "render_encounter", "sensor_options", "SUITES"):
        from . import writer

        return getattr(writer, name)
    if name == "WORLDS":
        from .worlds import WORLDS

        return WORLDS
    raise AttributeError(name)

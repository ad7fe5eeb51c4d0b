"""Synthetic encounter worlds: a numpy CPU renderer, two seeded world generators
(``cad-intersection``, ``indoor-team``), simulated depth sources, and the writer
behind ``cerpe synth`` (mocap-style dataset with manifest).

Public API (imported lazily so ``import cerpe.synth`` stays cheap)::

    generate_suite(world, out_dir, conf) -> manifest path
    generate_suites(name, out_root) -> {setting: manifest path}     # SUITES: fixture, paper-default
    render_encounter(world, seed, index, conf) -> cerpe.scene.Encounter   (in memory)
    SensorDepthSim, MonoDepthSim, sensor_options                     (MetricDepthSource simulations)
"""
from __future__ import annotations

from .errors import SynthError

__all__ = ["SynthError", "generate_suite", "generate_suites", "render_encounter", "SUITES", "WORLDS",
           "SensorDepthSim", "MonoDepthSim"]


def __getattr__(name: str):
    if name in ("generate_suite", "generate_suites", "render_encounter", "SUITES"):
        from . import writer

        return getattr(writer, name)
    if name == "WORLDS":
        from .worlds import WORLDS

        return WORLDS
    if name in ("SensorDepthSim", "MonoDepthSim", "sensor_options"):
        from . import depthsim

        return getattr(depthsim, name)
    raise AttributeError(name)

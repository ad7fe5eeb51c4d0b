"""Seeded procedural textures, evaluated per pixel in surface (world) units: the material
kinds and what a shader is given.

Every material is a function ``shade(inp: ShadeInput) -> [N,3] float albedo in [0,1]``
of the hit points of one material kind. Texture coordinates are metres on the
surface (``u`` along a face, ``v`` up on vertical faces), so texture density is
constant on surfaces whatever the distance. The shaders: :mod:`cerpe.synth.materials_outdoor`
and :mod:`cerpe.synth.materials_indoor`, one per kind in :data:`cerpe.synth.shaders.SHADERS`;
their noise: :mod:`cerpe.synth.noise`.

Everything here is deterministic in its inputs; there is no global random state.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from .noise import mix

# material kinds (index into shaders.SHADERS)
GROUND, FACADE, ROOF, CAR, POSTER, WALL, FLOOR, CEILING, WOOD, BOOKS, CARDBOARD, ROBOT, PLAIN = range(13)
KIND_NAMES = ("ground", "facade", "roof", "car", "poster", "wall", "floor", "ceiling", "wood", "books",
              "cardboard", "robot", "plain")


@dataclass
class ShadeContext:
    """World-level information shaders need beyond a face.

    Attributes:
        roads: ``[R,6]`` rows ``(axis, centre_m, half_width_m, start_m, end_m, lanes_per_dir)``;
            axis 0 = road along world x, 1 = along world y (cad worlds only).
        outdoor: sky, sun and haze (True) or a closed, evenly lit room (False).
        light_dir: unit vector towards the light (world, z up).
    """

    roads: np.ndarray = field(default_factory=lambda: np.zeros((0, 6)))
    outdoor: bool = True
    light_dir: tuple[float, float, float] = (-0.45, -0.6, 0.66)


@dataclass
class ShadeInput:
    """Hit points of one material kind. All arrays have length ``N``.

    ``u, v`` surface metres; ``lu, lv`` face extents (m); ``xw`` world points ``[N,3]``;
    ``foot`` pixel footprint on the surface (m); ``seed`` per-face int keys (:class:`PerFace`); ``color``
    per-face base colour ``[N,3]``; ``prm`` per-face parameters ``[N,4]``.
    """

    u: np.ndarray
    v: np.ndarray
    lu: np.ndarray
    lv: np.ndarray
    xw: np.ndarray
    foot: np.ndarray
    seed: np.ndarray
    color: np.ndarray
    prm: np.ndarray
    ctx: ShadeContext


def subset(s: ShadeInput, idx: np.ndarray) -> ShadeInput:
    """The hit points ``idx`` of ``s`` (shaders evaluate costly layers only where needed)."""
    return ShadeInput(s.u[idx], s.v[idx], s.lu[idx], s.lv[idx], s.xw[idx], s.foot[idx], s.seed[idx],
                      s.color[idx], s.prm[idx], s.ctx)  # PerFace.__getitem__ keeps per-face hashing


def layered(base: np.ndarray, weight: np.ndarray, s: ShadeInput, layer) -> np.ndarray:
    """Blend ``layer(subset)`` over ``base`` where ``weight > 0``; ``layer`` sees only those points."""
    idx = np.flatnonzero(weight > 0)
    if idx.size:
        base = base.copy()
        base[idx] = mix(base[idx], layer(subset(s, idx), idx), weight[idx])
    return base

"""Seeded band-limited noise and colour helpers for the procedural textures (:mod:`cerpe.synth.textures`).

Noise is band-limited value noise: a few fixed ``256x256`` tiles of Gaussian-
filtered white noise sampled bilinearly (``cv2.remap``, wrapping) at several
octaves. Each octave is rotated and offset by a hash of the face seed, so that no
two faces (and no two octaves) share a period. Octaves finer than the pixel's
footprint on the surface are faded out (a cheap mip-map), which keeps far
surfaces from aliasing into flickering noise that no detector could match.
Edges are anti-aliased analytically (:func:`coverage`). Everything here is
deterministic in its inputs; there is no global random state.
"""
from __future__ import annotations

from functools import lru_cache

import cv2
import numpy as np

TILE = 256
N_TILES = 4
# fixed per-octave rotations (radians): octaves never share lattice axes
_OCT_ANGLES = (0.0, 0.61, 1.37, 2.19, 0.93, 2.71, 1.83)

def F32(values) -> np.ndarray:
    """A float32 constant: shaders run in float32 and numpy promotes on any float64 operand."""
    return np.asarray(values, dtype=np.float32)


class PerFace:
    """Per-pixel integer keys that come from few faces: ``seeds[idx]``, hashed per face.

    Hashing ``seeds`` (length F) and gathering with ``idx`` (length N) costs one
    gather instead of a dozen full-length integer passes; ``+ int`` shifts all seeds.
    """

    __slots__ = ("idx", "seeds")

    def __init__(self, idx: np.ndarray, seeds: np.ndarray):
        self.idx, self.seeds = idx, np.asarray(seeds, np.int64)

    def __add__(self, k: int) -> "PerFace":
        return PerFace(self.idx, self.seeds + int(k))

    def __getitem__(self, sel) -> "PerFace":
        return PerFace(self.idx[sel], self.seeds)

    def values(self) -> np.ndarray:
        return self.seeds[self.idx]


def hash_u32(*keys) -> np.ndarray:
    """Vectorised integer hash (murmur3 finaliser) of any number of int keys/arrays.

    A :class:`PerFace` first key is hashed per face and gathered when the other
    keys are scalars (the common case), else expanded to per-pixel values.
    """
    if keys and isinstance(keys[0], PerFace):
        pf = keys[0]
        if all(np.ndim(k) == 0 for k in keys[1:]):
            return _hash_u32(pf.seeds, *keys[1:])[pf.idx]
        keys = (pf.values(),) + keys[1:]
    return _hash_u32(*[k.values() if isinstance(k, PerFace) else k for k in keys])


def _hash_u32(*keys) -> np.ndarray:
    h = np.uint32(0x9E3779B9)
    h = np.full(np.broadcast(*[np.asarray(k) for k in keys]).shape, h, dtype=np.uint32)
    with np.errstate(over="ignore"):
        for k in keys:
            k = np.asarray(k).astype(np.int64).astype(np.uint64).astype(np.uint32)
            h = h ^ (k * np.uint32(0xCC9E2D51))
            h = (h << np.uint32(13)) | (h >> np.uint32(19))
            h = h * np.uint32(5) + np.uint32(0xE6546B64)
        h ^= h >> np.uint32(16)
        h *= np.uint32(0x85EBCA6B)
        h ^= h >> np.uint32(13)
        h *= np.uint32(0xC2B2AE35)
        h ^= h >> np.uint32(16)
    return h


def hash_unit(*keys) -> np.ndarray:
    """Hash to float32 uniform in ``[0, 1)``."""
    return hash_u32(*keys).astype(np.float32) * np.float32(1.0 / 4294967296.0)


@lru_cache(maxsize=None)
def _tile(i: int) -> np.ndarray:
    """Band-limited noise tile ``[TILE,TILE] float32``, zero mean, unit std, wrapping."""
    from scipy.ndimage import gaussian_filter

    rng = np.random.default_rng(1000 + i)
    t = gaussian_filter(rng.standard_normal((TILE, TILE)), sigma=1.1, mode="wrap")
    t = (t - t.mean()) / t.std()
    return t.astype(np.float32)


def _remap(tile: np.ndarray, x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Bilinear wrap-around lookup of ``tile`` at float texel coords (any length)."""
    n = x.shape[0]
    if n == 0:
        return np.zeros(0, np.float32)
    w = 1024
    m = -(-n // w) * w
    X = np.zeros(m, np.float32)
    Y = np.zeros(m, np.float32)
    # remap needs small coordinates (fixed-point internally): wrap first. float32 keeps
    # 1/128 texel at 10^5 texels from the origin, ample for these worlds.
    np.mod(x, TILE, out=X[:n])
    np.mod(y, TILE, out=Y[:n])
    out = cv2.remap(tile, X.reshape(-1, w), Y.reshape(-1, w), cv2.INTER_LINEAR, borderMode=cv2.BORDER_WRAP)
    return out.ravel()[:n]


def noise(x: np.ndarray, y: np.ndarray, texel_m: float, key, octave: int = 0) -> np.ndarray:
    """One octave of value noise (zero mean, ~unit std) with texel size ``texel_m``.

    ``key`` (int or per-point int array) decorrelates faces: it picks the tile
    and the offset; the octave index picks the rotation.
    """
    a = _OCT_ANGLES[octave % len(_OCT_ANGLES)]
    ca, sa = float(np.cos(a) / texel_m), float(np.sin(a) / texel_m)
    ox = hash_unit(key, octave, 1) * TILE
    oy = hash_unit(key, octave, 2) * TILE
    xs = ca * x - sa * y + ox
    ys = sa * x + ca * y + oy
    return _remap(_tile(octave % N_TILES), xs, ys)


def fbm(x: np.ndarray, y: np.ndarray, foot: np.ndarray, texel_m: float, octaves: int, key,
        gain: float = 0.55) -> np.ndarray:
    """Multi-octave noise with footprint fading (finer octaves vanish when smaller than a pixel).

    Returns roughly zero-mean values with std <= 1 (less where detail is faded).
    """
    out = np.zeros(x.shape[0], np.float32)
    amp, tot, tex = 1.0, 0.0, texel_m
    for k in range(octaves):
        w = np.clip(tex / np.maximum(foot, 1e-6) - 0.5, 0.0, 1.0).astype(np.float32)
        if np.any(w > 0):
            out += (amp * w) * noise(x, y, tex, key, k)
        tot += amp
        amp *= gain
        tex *= 0.5
    return out / np.float32(np.sqrt(tot))


def coverage(signed_dist: np.ndarray, foot: np.ndarray) -> np.ndarray:
    """Anti-aliased inside-ness of an edge: 1 deep inside (``d>0``), 0 outside, linear over a pixel."""
    return np.clip(0.5 + signed_dist / np.maximum(foot, 1e-6), 0.0, 1.0)


def box_cov(a: np.ndarray, b: np.ndarray, a0, a1, b0, b1, foot) -> np.ndarray:
    """Anti-aliased coverage of the axis-aligned rectangle ``[a0,a1]x[b0,b1]``."""
    d = np.minimum(np.minimum(a - a0, a1 - a), np.minimum(b - b0, b1 - b))
    return coverage(d, foot)


def mix(c0: np.ndarray, c1, w: np.ndarray) -> np.ndarray:
    """Blend colours ``c0 [N,3]`` and ``c1 [N,3] or [3]`` with weight ``w [N]`` on c1."""
    w = w[:, None]
    return c0 * (1.0 - w) + np.asarray(c1, np.float32) * w


def palette(h: np.ndarray, sat: float = 0.7, val: float = 0.85) -> np.ndarray:
    """Hash in [0,1) -> saturated RGB ``[N,3]`` (hue wheel)."""
    hue = h * 6.0
    r = np.clip(np.abs(hue - 3.0) - 1.0, 0, 1)
    g = np.clip(2.0 - np.abs(hue - 2.0), 0, 1)
    b = np.clip(2.0 - np.abs(hue - 4.0), 0, 1)
    rgb = np.stack([r, g, b], 1)
    val = np.asarray(val, np.float32)
    return (val[:, None] if val.ndim == 1 else val) * (1.0 - sat + sat * rgb)

"""Indoor materials of the ``indoor-team`` world: walls, floor, ceiling, furniture, robots, plain surfaces.

Shaders of :mod:`cerpe.synth.textures` (one per material kind): ``[N,3]`` float32 albedo in
[0,1] from the hit points of one kind, in surface metres.
"""
from __future__ import annotations

import numpy as np

from .noise import F32, box_cov, coverage, fbm, hash_unit, mix, palette
from .textures import ShadeInput


def shade_wall(s: ShadeInput) -> np.ndarray:
    """Room wall: wallpaper (stripes, blotch pattern or painted plaster, per wall),
    skirting board, sockets, scuffs. ``prm = (style 0|1|2, 0, 0, 0)``."""
    u, v, f, k = s.u, s.v, s.foot, s.seed
    style = s.prm[:, 0]
    g = fbm(u, v, f, 0.015, 5, k + 1)
    g2 = fbm(u, v, f, 0.25, 3, k + 2)
    base = s.color * (1.0 + 0.06 * g + 0.08 * g2)[:, None]
    stripes = base * (1.0 - 0.18 * (np.mod(u, 0.3) < 0.1).astype(np.float32)
                      - 0.06 * (np.mod(u + 0.05, 0.3) < 0.02).astype(np.float32))[:, None]
    blot = fbm(u, v, f, 0.04, 4, k + 3)
    pattern = base * (1.0 - 0.22 * (blot > 0.35).astype(np.float32) + 0.1 * (blot < -0.5).astype(np.float32))[:, None]
    out = np.where((style < 0.5)[:, None], stripes, np.where((style < 1.5)[:, None], pattern, base))
    skirt = coverage(0.1 - v, f)
    out = mix(out, F32([0.9, 0.88, 0.84]) * (1 + 0.04 * g)[:, None], skirt)
    out = mix(out, F32([0.5, 0.48, 0.45]), coverage(0.006 - np.abs(v - 0.1), f))
    # sockets every ~2.3 m with per-socket jitter
    sc = np.floor(u / 2.3)
    sx = sc * 2.3 + 0.5 + 1.2 * hash_unit(k, sc)
    sock = box_cov(u, v, sx, sx + 0.08, 0.28, 0.36, f) * (hash_unit(k, sc, 2) < 0.7)
    out = mix(out, F32([0.95, 0.95, 0.93]), sock)
    holes = (np.hypot(u - sx - 0.025, v - 0.32) < 0.008) | (np.hypot(u - sx - 0.055, v - 0.32) < 0.008)
    out = np.where((holes & (sock > 0.5))[:, None], F32([0.2, 0.2, 0.2]), out)
    scuff = np.clip(fbm(u, v * 3, f, 0.08, 3, k + 4) - 0.8, 0, None) * (v < 0.6)
    return out * (1.0 - 0.5 * scuff)[:, None]


def shade_floor(s: ShadeInput) -> np.ndarray:
    """Wooden plank floor: staggered planks with per-plank tone and grain."""
    x, y, f, k = s.u, s.v, s.foot, s.seed
    pw = 0.16
    row = np.floor(y / pw)
    plen = 1.2 + 0.8 * hash_unit(k, row, 1)
    off = hash_unit(k, row, 2) * plen
    pid = np.floor((x + off) / plen)
    tone = 0.75 + 0.35 * hash_unit(k, row, pid)
    grain = fbm((x + off) * 0.12, y, f * 0.5, 0.02, 4, k + 5)
    knot = fbm(x, y, f, 0.06, 3, k + 6)
    col = s.color * (tone * (1.0 + 0.12 * grain + 0.05 * knot))[:, None]
    gap = np.minimum(np.minimum(y - row * pw, (row + 1) * pw - y), np.minimum(np.mod(x + off, plen), plen - np.mod(x + off, plen)))
    return mix(col, col * 0.45, 1.0 - coverage(gap - 0.004, f))


def shade_ceiling(s: ShadeInput) -> np.ndarray:
    u, v, f = s.u, s.v, s.foot
    g = fbm(u, v, f, 0.01, 4, s.seed + 7)
    t = 0.6
    d = np.minimum(np.minimum(np.mod(u, t), t - np.mod(u, t)), np.minimum(np.mod(v, t), t - np.mod(v, t)))
    col = s.color * (1.0 + 0.08 * g)[:, None]
    return mix(col, col * 0.6, 1.0 - coverage(d - 0.012, f))


def shade_wood(s: ShadeInput) -> np.ndarray:
    """Furniture wood: grain stretched along ``u``, rings, slight planks."""
    u, v, f, k = s.u, s.v, s.foot, s.seed
    grain = fbm(u * 0.1, v, f * 0.3, 0.012, 4, k + 3)
    ring = np.sin((v + 0.05 * fbm(u, v, f, 0.15, 2, k + 4)) * 90.0)
    return s.color * (1.0 + 0.14 * grain + 0.06 * ring)[:, None]


def shade_books(s: ShadeInput) -> np.ndarray:
    """Shelf front: boards every 0.38 m, rows of books of hashed width, height,
    colour and label band; dark back panel above them."""
    u, v, f, k = s.u, s.v, s.foot, s.seed
    sh = 0.38
    row = np.floor(v / sh)
    rv = v - row * sh
    bw = 0.028 + 0.02 * hash_unit(k, row, 1)
    bi = np.floor(u / bw + hash_unit(k, row, 2) * 10)
    bh = 0.2 + 0.13 * hash_unit(k, row, bi)
    gapb = hash_unit(k, row, bi, 3) < 0.08
    book = palette(hash_unit(k, row, bi, 4), 0.55, 0.35 + 0.5 * hash_unit(k, row, bi, 5))
    lab = coverage(0.012 - np.abs(rv - bh * (0.55 + 0.3 * hash_unit(k, row, bi, 6))), f)
    book = mix(book, F32([0.9, 0.85, 0.6]), lab)
    spine = np.abs((u / bw + hash_unit(k, row, 2) * 10) - bi - 0.5) * 2
    book = book * (1.0 - 0.25 * spine ** 4)[:, None]
    back = s.color * 0.35
    out = np.where(((rv < bh) & ~gapb)[:, None], book, back * np.ones_like(book))
    board = coverage(0.025 - rv, f) + coverage(0.025 - (sh - rv), f) * 0
    out = mix(out, s.color * (1.0 + 0.1 * fbm(u * 0.1, v, f, 0.01, 3, k))[:, None], np.clip(board, 0, 1))
    edge = coverage(0.03 - np.minimum(u, s.lu - u), f)
    return mix(out, s.color, edge)


def shade_cardboard(s: ShadeInput) -> np.ndarray:
    """Cardboard box: corrugation, tape, a label with text bars and a barcode."""
    u, v, f, k = s.u, s.v, s.foot, s.seed
    g = fbm(u, v, f, 0.01, 4, k + 1)
    col = s.color * (1.0 + 0.08 * g + 0.03 * np.sin(v * 400.0) * (f < 0.003))[:, None]
    tape = coverage(0.025 - np.abs(u - s.lu * 0.5), f) * (v > s.lv - 0.12)
    col = mix(col, F32([0.75, 0.6, 0.35]), tape)
    lx, ly = s.lu * (0.15 + 0.3 * hash_unit(k, 3)), s.lv * (0.2 + 0.3 * hash_unit(k, 4))
    lw, lh = 0.12 + 0.08 * hash_unit(k, 5), 0.08 + 0.05 * hash_unit(k, 6)
    lab = box_cov(u, v, lx, lx + lw, ly, ly + lh, f)
    line = (np.mod(v - ly, 0.018) < 0.008) & (hash_unit(k, np.floor((v - ly) / 0.018), np.floor((u - lx) / 0.012)) < 0.7)
    bar = (v - ly < lh * 0.35) & (hash_unit(k, np.floor((u - lx) / 0.004), 9) < 0.5)
    ink = (line & (v - ly > lh * 0.4)) | bar
    labc = np.where(ink[:, None], F32([0.1, 0.1, 0.1]), F32([0.95, 0.95, 0.92]))
    col = mix(col, labc, lab)
    arrow = (np.abs(u - (lx + lw + 0.06)) < 0.015) & (v > ly) & (v < ly + lh)
    return np.where(arrow[:, None], F32([0.15, 0.15, 0.15]), col)


def shade_robot(s: ShadeInput) -> np.ndarray:
    """Small robot chassis: dark plastic, a coloured band, a checker marker."""
    u, v, f = s.u, s.v, s.foot
    col = F32([0.15, 0.15, 0.17]) * (1.0 + 0.1 * fbm(u, v, f, 0.01, 3, s.seed))[:, None]
    band = coverage(0.02 - np.abs(v - s.lv * 0.6), f)
    col = mix(col, s.color, band)
    chk = ((np.floor(u / 0.03) + np.floor(v / 0.03)) % 2 == 0) & (np.abs(u - s.lu / 2) < 0.06) & (np.abs(v - s.lv * 0.3) < 0.03)
    return np.where(chk[:, None], F32([0.9, 0.9, 0.9]), col)


def shade_plain(s: ShadeInput) -> np.ndarray:
    return s.color * (1.0 + 0.12 * fbm(s.u, s.v, s.foot, 0.03, 4, s.seed))[:, None]

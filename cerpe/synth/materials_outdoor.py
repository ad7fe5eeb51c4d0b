"""Outdoor materials of the ``cad-intersection`` world: streets, facades, roofs, vehicles, posters.

Shaders of :mod:`cerpe.synth.textures` (one per material kind): ``[N,3]`` float32 albedo in
[0,1] from the hit points of one kind, in surface metres.
"""
from __future__ import annotations

import numpy as np

from .noise import F32, box_cov, coverage, fbm, hash_u32, hash_unit, mix, palette
from .textures import ShadeInput, layered, subset


def shade_ground(s: ShadeInput) -> np.ndarray:
    """Streets: asphalt with grain and patches, lane markings, crosswalks, stop
    lines, manholes; concrete sidewalk slabs elsewhere; kerbs at road edges."""
    x, y = s.xw[:, 0], s.xw[:, 1]
    n = x.shape[0]
    n_in = np.zeros(n, np.int32)
    kerb = np.zeros(n, bool)
    for r in s.ctx.roads:
        ax, c, hw, s0, s1 = int(r[0]), float(r[1]), float(r[2]), float(r[3]), float(r[4])
        along, lat = (x, y - c) if ax == 0 else (y, x - c)
        span = (along > s0) & (along < s1)
        n_in += (np.abs(lat) < hw) & span
        kerb |= (np.abs(lat) < hw + 0.25) & span
    road = n_in > 0
    col = np.zeros((n, 3), np.float32)
    i_side = np.flatnonzero(~road)
    if i_side.size:
        q = subset(s, i_side)
        col[i_side] = _sidewalk(q) * np.where(kerb[i_side], 1.15, 1.0)[:, None]
    i_road = np.flatnonzero(road)
    if i_road.size:
        col[i_road] = _asphalt(subset(s, i_road), n_in[i_road])
    return col


def _sidewalk(s: ShadeInput) -> np.ndarray:
    """Concrete: 1.5 m slabs with per-slab tone, joints, grime and fine grain."""
    x, y, f = s.xw[:, 0], s.xw[:, 1], s.foot
    sx, sy = np.floor(x / 1.5), np.floor(y / 1.5)
    slab = 0.62 + 0.14 * (hash_unit(sx, sy, 7) - 0.5)
    jx = np.minimum(x - sx * 1.5, (sx + 1) * 1.5 - x)
    jy = np.minimum(y - sy * 1.5, (sy + 1) * 1.5 - y)
    joint = 1.0 - 0.4 * (1.0 - coverage(np.minimum(jx, jy) - 0.015, f))
    g = fbm(x, y, f, 0.04, 6, s.seed + 11)
    stain = np.clip(fbm(x, y, f, 0.5, 3, s.seed + 12), 0, None)
    return (slab * joint * (1.0 + 0.16 * g - 0.12 * stain))[:, None] * F32([1.0, 0.98, 0.93])


def _asphalt(s: ShadeInput, n_in: np.ndarray) -> np.ndarray:
    """Asphalt with grain, repairs, manholes and paint (only outside crossings: ``n_in == 1``)."""
    x, y, f, key = s.xw[:, 0], s.xw[:, 1], s.foot, s.seed
    n = x.shape[0]
    grain = fbm(x, y, f, 0.025, 5, key + 21)
    patch = fbm(x, y, f, 1.2, 2, key + 23)
    tone = 0.27 + 0.09 * grain + 0.05 * patch
    asph = tone[:, None] * F32([1.0, 1.0, 1.04])
    # manholes and drains on a 13 m lattice
    mx, my = np.floor(x / 13.0), np.floor(y / 13.0)
    hx = (mx + 0.2 + 0.6 * hash_unit(mx, my, 3)) * 13.0
    hy = (my + 0.2 + 0.6 * hash_unit(mx, my, 4)) * 13.0
    rr = np.hypot(x - hx, y - hy)
    man = coverage(0.35 - rr, f) * (hash_unit(mx, my, 5) < 0.6)
    ring = np.cos(rr * 60.0) * 0.08
    asph = mix(asph, (0.18 + ring)[:, None] * F32([1.0, 1.0, 1.0]), man)
    paint = np.zeros(n, np.float32)
    yellow = np.zeros(n, np.float32)
    single = n_in == 1
    roads = s.ctx.roads
    for r in roads:
        ax, c, hw, s0, s1, lanes = int(r[0]), float(r[1]), float(r[2]), float(r[3]), float(r[4]), max(int(r[5]), 1)
        along, lat = (x, y - c) if ax == 0 else (y, x - c)
        on = np.flatnonzero(single & (np.abs(lat) < hw) & (along > s0) & (along < s1))
        if not on.size:
            continue
        along, lat, fo = along[on], lat[on], f[on]
        lane_w = hw / lanes
        alat = np.abs(lat)
        yellow[on] = coverage(0.06 - np.abs(alat - 0.12), fo)
        p = coverage(0.08 - np.abs(alat - (hw - 0.35)), fo)
        if lanes > 1:
            dash = (along % 9.0) < 3.0
            for k in range(1, lanes):
                p = np.maximum(p, coverage(0.07 - np.abs(alat - k * lane_w), fo) * dash)
        for r2 in roads:  # crosswalk and stop line before every road that crosses this one
            if int(r2[0]) == ax or not (r2[3] - hw <= c <= r2[4] + hw):
                continue
            dd = np.abs(along - float(r2[1])) - float(r2[2])
            zebra = (dd > 0.8) & (dd < 3.8) & (alat < hw - 0.5)
            stripe = coverage(0.25 - np.abs(((lat + 100.0) % 1.0) - 0.5), fo)
            p = np.maximum(p, zebra * stripe)
            p = np.maximum(p, coverage(0.2 - np.abs(dd - 4.6), fo) * (alat < hw - 0.4))
        paint[on] = p
    wear = np.clip(0.85 + 0.3 * fbm(x, y, f, 0.04, 3, key + 31), 0.3, 1.0)
    asph = mix(asph, F32([0.86, 0.86, 0.84]), paint * wear)
    return mix(asph, F32([0.85, 0.68, 0.15]), yellow * wear)


def _window_glass(s: ShadeInput, wid: np.ndarray, cu: np.ndarray, cv: np.ndarray, ww, wh) -> np.ndarray:
    """Per-window glass: sky reflections, curtains, blinds or a lit room (hash ``wid``)."""
    h = hash_unit(wid, 1)
    t = cv / wh
    refl = (0.25 + 0.35 * t + 0.08 * hash_unit(wid, 2))[:, None] * F32([0.75, 0.85, 1.0])
    curtain_col = palette(hash_unit(wid, 3), 0.5, 0.75)
    folds = 0.8 + 0.2 * np.sin(cu / ww * (8 + 10 * hash_unit(wid, 4)) * np.pi)
    curtain = curtain_col * folds[:, None]
    blinds = (0.55 + 0.25 * (np.sin(cv * 2 * np.pi / 0.05) > 0).astype(np.float32))[:, None] * F32([0.95, 0.93, 0.88])
    lit = F32([0.95, 0.82, 0.5]) * (0.8 + 0.2 * t)[:, None]
    out = np.where((h < 0.45)[:, None], refl, curtain)
    out = np.where(((h >= 0.75) & (h < 0.9))[:, None], blinds, out)
    out = np.where((h >= 0.9)[:, None], lit, out)
    # half-drawn curtain over a reflection
    half = (h < 0.45) & (hash_unit(wid, 5) < 0.4) & (cu < ww * (0.2 + 0.5 * hash_unit(wid, 6)))
    return np.where(half[:, None], curtain, out)


def shade_facade(s: ShadeInput) -> np.ndarray:
    """Building facade: plaster or brick, a window grid with per-window variation
    (frames, sills, glass/curtain/blind/lit), shop windows on the ground floor,
    a cornice; ``prm = (floor_height_m, window_cell_m, style 0 plaster|1 brick, shop 0|1)``."""
    u, v, f, key = s.u, s.v, s.foot, s.seed
    floor_h, cell, style, shop = s.prm[:, 0], s.prm[:, 1], s.prm[:, 2], s.prm[:, 3]
    base = s.color
    g1 = fbm(u, v, f, 0.6, 3, key + 1)
    g2 = fbm(u, v, f, 0.02, 5, key + 2)
    plaster = base * (1.0 + 0.10 * g1 + 0.07 * g2)[:, None]
    # streaks of grime running down from the top
    streak = fbm(u * 6.0, v * 0.25, f * 6.0, 0.5, 2, key + 3)
    plaster *= (1.0 - 0.06 * np.clip(streak, 0, None))[:, None]
    bh, bw = 0.075, 0.24
    row = np.floor(v / bh)
    bu = u + (row % 2) * bw * 0.5
    col_ = np.floor(bu / bw)
    mort = np.minimum(np.minimum(v - row * bh, (row + 1) * bh - v), np.minimum(bu - col_ * bw, (col_ + 1) * bw - bu))
    btone = 0.8 + 0.35 * hash_unit(row, col_, key)
    brick = base * (btone * (1.0 + 0.06 * g2))[:, None]
    brick = mix(brick, F32([0.72, 0.7, 0.66]), 1.0 - coverage(mort - 0.008, f))
    wall = np.where((style > 0.5)[:, None], brick, plaster)
    # window grid, centred on the face, only whole cells
    ncell = np.maximum(np.floor(s.lu / cell), 1.0)
    margin = (s.lu - ncell * cell) * 0.5
    uu = u - margin
    ix = np.floor(uu / cell)
    iy = np.floor(v / floor_h)
    cu = uu - ix * cell
    cv = v - iy * floor_h
    n_floors = np.floor(s.lv / floor_h)
    ok = (ix >= 0) & (ix < ncell) & (iy < n_floors - 0.5) & ~((iy == 0) & (shop > 0.5))
    ww = cell * (0.45 + 0.15 * hash_unit(key, 9))
    wh = floor_h * 0.5
    x0 = (cell - ww) * 0.5
    y0 = floor_h * 0.3
    inwin = box_cov(cu, cv, x0, x0 + ww, y0, y0 + wh, f) * ok

    def window(q: ShadeInput, i: np.ndarray) -> np.ndarray:
        wid = hash_u32(q.seed, ix[i], iy[i]).astype(np.int64)
        a, b, w_, h_ = cu[i] - x0[i], cv[i] - y0[i], ww[i], wh[i]
        glass = _window_glass(q, wid, a, b, w_, h_)
        frame_w = 0.07
        inglass = box_cov(a, b, frame_w, w_ - frame_w, frame_w, h_ - frame_w, q.foot)
        mull = coverage(0.025 - np.abs(a - w_ * 0.5), q.foot) * (hash_unit(q.seed, 8) < 0.6)
        frame_col = np.where((hash_unit(q.seed, 10) < 0.5)[:, None], F32([0.92, 0.92, 0.9]),
                             F32([0.25, 0.22, 0.2]))
        return mix(frame_col, glass, inglass * (1.0 - mull))

    out = layered(wall, inwin, s, window)
    sill = box_cov(cu, cv, x0 - 0.08, x0 + ww + 0.08, y0 - 0.07, y0, f) * ok
    out = mix(out, base * 0.7 + 0.2, sill)
    # ground-floor shop fronts: big glass bays with mullions and a coloured fascia
    bay = 1.6
    isshop = ((shop > 0.5) & (v < floor_h)).astype(float)

    def shopfront(q: ShadeInput, i: np.ndarray) -> np.ndarray:
        su = np.mod(q.u, bay)
        sid = hash_u32(q.seed, np.floor(q.u / bay), 77).astype(np.int64)
        sglass = _window_glass(q, sid, su, q.v - 0.4, bay, 2.2)
        sg = box_cov(su, q.v, 0.08, bay - 0.08, 0.4, 2.6, q.foot)
        shopc = mix(F32([0.2, 0.2, 0.22]) * np.ones_like(q.color), sglass, sg)
        fascia = box_cov(q.u, q.v, -1.0, q.lu + 1.0, 2.75, floor_h[i] - 0.1, q.foot)
        fcol = palette(hash_unit(q.seed, 12), 0.8, 0.7) * (
            1.0 + 0.25 * (np.sin(q.u * 9.0 + 3 * hash_unit(q.seed, 13)) > 0.6).astype(np.float32))[:, None]
        return mix(shopc, fcol, fascia)

    out = layered(out, isshop, s, shopfront)
    # cornice at the top, plinth at the bottom
    out = mix(out, base * 0.6, coverage(0.35 - (s.lv - v), f))
    out = mix(out, F32([0.35, 0.34, 0.33]) * (1.0 + 0.1 * g2)[:, None], coverage(0.25 - v, f))
    # ambient occlusion near the ground
    return out * (1.0 - 0.3 * np.exp(-v / 0.6))[:, None]


def shade_roof(s: ShadeInput) -> np.ndarray:
    g = fbm(s.u, s.v, s.foot, 0.05, 5, s.seed + 40)
    return s.color * (0.8 + 0.12 * g)[:, None]


def shade_car(s: ShadeInput) -> np.ndarray:
    """Vehicle box: tyres, paint, door seams, lights, a number plate, and glass:
    a band on tall single boxes (vans, cabs; height > 1.2 m) or the whole of a
    cabin box. ``prm = (face 0 side|1 front|2 back|3 top|4 cabin, 0, 0, 0)``."""
    u, v, f = s.u, s.v, s.foot
    face = s.prm[:, 0]
    H, L = s.lv, s.lu
    g = fbm(u, v, f, 0.03, 4, s.seed + 50)
    paint = s.color * (1.0 + 0.05 * g + 0.15 * (v / np.maximum(H, 1e-3) - 0.5))[:, None]
    out = paint
    cabin = face > 3.5
    low = coverage(0.32 - v, f) * ~cabin
    out = mix(out, F32([0.08, 0.08, 0.09]), low)
    side = face < 0.5
    for wc in (0.9, -0.9):
        cx = np.where(wc > 0, wc, L + wc)
        r = np.hypot(u - cx, v - 0.34)
        tyre = coverage(0.34 - r, f) * side
        out = mix(out, F32([0.05, 0.05, 0.05]), tyre)
        rim = coverage(0.2 - r, f) * side
        spokes = 0.55 + 0.2 * (np.sin(5 * np.arctan2(v - 0.34, u - cx)) > 0).astype(np.float32)
        out = mix(out, spokes[:, None] * F32([1, 1, 1.02]), rim)
    seam = (coverage(0.012 - np.abs(u - L * 0.48), f) + coverage(0.012 - np.abs(u - L * 0.72), f)) * side * (v > 0.35) * (v < 0.9)
    out = mix(out, paint * 0.3, np.clip(seam, 0, 1))
    handle = (box_cov(u, v, L * 0.50, L * 0.50 + 0.18, 0.74, 0.78, f) + box_cov(u, v, L * 0.74, L * 0.74 + 0.18, 0.74, 0.78, f)) * side
    out = mix(out, paint * 0.5, np.clip(handle, 0, 1))
    gb0 = np.where(H > 2.2, H - 0.9, H - 0.62)
    gl = box_cov(u, v, 0.25, L - 0.25, gb0, H - 0.08, f) * (face < 2.5) * (H > 1.2)
    t = (v - gb0) / 0.6
    glass = (0.12 + 0.25 * t + 0.05 * g)[:, None] * F32([0.7, 0.8, 0.95])
    pillar = coverage(0.05 - np.abs(u - L * 0.5), f) * (side | cabin)
    out = mix(out, glass, gl * (1 - pillar))
    cab_glass = (0.12 + 0.3 * v / np.maximum(H, 1e-3) + 0.05 * g)[:, None] * F32([0.7, 0.8, 0.95])
    cab = box_cov(u, v, 0.1, L - 0.1, 0.04, H - 0.06, f) * (1 - pillar) * cabin
    out = mix(out, cab_glass, cab)
    front = np.abs(face - 1) < 0.5
    back = np.abs(face - 2) < 0.5
    for lx in (0.15, -0.15):
        x0 = np.where(lx > 0, 0.12, L - 0.42)
        lamp = box_cov(u, v, x0, x0 + 0.3, 0.62, 0.76, f)
        out = mix(out, F32([0.95, 0.95, 0.85]), lamp * front)
        out = mix(out, F32([0.8, 0.08, 0.05]), lamp * back)
    plate = box_cov(u, v, L * 0.5 - 0.26, L * 0.5 + 0.26, 0.42, 0.53, f) * (front | back)
    chars = (hash_unit(s.seed, np.floor((u - L * 0.5) / 0.06), 5) < 0.7) & (np.abs(u - L * 0.5) < 0.22) & (np.abs(v - 0.475) < 0.035)
    pc = np.where(chars[:, None], F32([0.1, 0.1, 0.1]), F32([0.92, 0.92, 0.85]))
    out = mix(out, pc, plate)
    return out


def shade_poster(s: ShadeInput) -> np.ndarray:
    """Posters, billboards, truck adverts: hashed colour blocks, a disc, a photo-
    like noise panel and lines of 'text'. Each face seed is one design."""
    a = s.u / np.maximum(s.lu, 1e-6)
    b = 1.0 - s.v / np.maximum(s.lv, 1e-6)  # top-down
    k = s.seed
    f = s.foot / np.maximum(np.minimum(s.lu, s.lv), 1e-6)
    out = palette(hash_unit(k, 1), 0.35, 0.95)
    for j in range(3):
        x0, y0 = hash_unit(k, j, 10) * 0.7, hash_unit(k, j, 11) * 0.6
        out = mix(out, palette(hash_unit(k, j, 12), 0.8, 0.8), box_cov(a, b, x0, x0 + 0.15 + 0.3 * hash_unit(k, j, 13),
                                                                        y0, y0 + 0.1 + 0.3 * hash_unit(k, j, 14), f))
    cx, cy = 0.2 + 0.6 * hash_unit(k, 20), 0.2 + 0.35 * hash_unit(k, 21)
    r = np.hypot(a - cx, (b - cy) * s.lv / np.maximum(s.lu, 1e-6))
    out = mix(out, palette(hash_unit(k, 22), 0.9, 0.9), coverage(0.08 + 0.12 * hash_unit(k, 23) - r, f))
    # photo panel: coloured noise
    px0, py0 = hash_unit(k, 30) * 0.5, 0.05 + hash_unit(k, 31) * 0.3
    inp = box_cov(a, b, px0, px0 + 0.45, py0, py0 + 0.3, f)
    ph = fbm(s.u, s.v, s.foot, 0.05, 4, k + 33)
    ph2 = fbm(s.u, s.v, s.foot, 0.12, 3, k + 34)
    photo = np.clip(np.stack([0.5 + 0.35 * ph, 0.5 + 0.3 * ph2, 0.5 - 0.3 * ph], 1), 0, 1)
    out = mix(out, photo, inp)
    # text lines in the lower part
    row = np.floor(b / 0.055)
    word = np.floor(a / 0.09 + hash_unit(k, row) * 3)
    letter = np.floor(a / 0.018)
    txt = (b > 0.62) & (b < 0.95) & (a > 0.06) & (a < 0.94) & ((b / 0.055 - row) < 0.6)
    txt &= (hash_unit(k, row, word) < 0.75) & (hash_unit(k, row, letter, 7) < 0.8)
    out = np.where(txt[:, None], palette(hash_unit(k, 40), 0.3, 0.15) * np.ones_like(out), out)
    border = 1.0 - box_cov(a, b, 0.02, 0.98, 0.02, 0.98, f)
    out = mix(out, F32([0.95, 0.95, 0.95]), border)
    return out * (1.0 + 0.05 * fbm(s.u, s.v, s.foot, 0.02, 3, k + 50))[:, None]

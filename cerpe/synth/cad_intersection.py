"""The ``cad-intersection`` world: vehicles meeting at urban junctions (one of four layouts).

Trajectories are smooth by construction: vehicles follow lane lines joined by circular arcs at
constant speed, a forward camera 1.5 m high; a truck crosses the junction and occludes. Streets,
buildings with shopfronts, parked cars, kiosks and lamp posts line the roads. Frames and poses:
:mod:`cerpe.synth.plan`.
"""
from __future__ import annotations

import numpy as np

from ..scene import CameraIntrinsics
from . import textures as tx
from .errors import SynthError
from .plan import EncounterPlan, MovingObject, camera_pose, yaw_pose
from .renderer import FaceSet, Material, box, quad

CAD_LAYOUTS = ("cross", "t-junction", "offset-cross", "boulevard")


class Path2D:
    """Planar path from line segments and arcs, sampled densely; query by arc length."""

    def __init__(self, pts: np.ndarray):
        self.pts = np.asarray(pts, float)
        seg = np.diff(self.pts, axis=0)
        self.s = np.concatenate([[0.0], np.cumsum(np.linalg.norm(seg, axis=1))])
        self.heading = np.unwrap(np.arctan2(seg[:, 1], seg[:, 0]))
        self.heading = np.concatenate([self.heading, self.heading[-1:]])

    @property
    def length(self) -> float:
        return float(self.s[-1])

    def at(self, s: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        s = np.clip(np.asarray(s, float), 0.0, self.length)
        x = np.interp(s, self.s, self.pts[:, 0])
        y = np.interp(s, self.s, self.pts[:, 1])
        h = np.interp(s, self.s, self.heading)
        return x, y, h

    def closest_s(self, p: np.ndarray) -> float:
        return float(self.s[np.argmin(np.linalg.norm(self.pts - np.asarray(p)[None], axis=1))])


def _line(a, b, step=0.05) -> np.ndarray:
    n = max(int(np.ceil(np.linalg.norm(np.subtract(b, a)) / step)), 1)
    return np.asarray(a) + np.linspace(0, 1, n + 1)[:, None] * (np.asarray(b) - np.asarray(a))


def _right(h: np.ndarray) -> np.ndarray:
    return np.array([h[1], -h[0]])


def _cad_roads(layout: str) -> np.ndarray:
    """``[R,6]`` roads ``(axis, centre, half_width, start, end, lanes_per_dir)``."""
    L = 160.0
    if layout == "cross":
        return np.array([[0, 0, 7, -L, L, 2], [1, 0, 6, -L, L, 1]], float)
    if layout == "t-junction":
        return np.array([[0, 0, 7, -L, L, 2], [1, 0, 6, -L, 0, 1]], float)
    if layout == "offset-cross":
        return np.array([[0, 0, 6.5, -L, L, 1], [1, -16, 5.5, 0, L, 1], [1, 16, 5.5, -L, 0, 1]], float)
    if layout == "boulevard":
        return np.array([[0, 0, 12, -L, L, 3], [1, 0, 6, -L, L, 1]], float)
    raise SynthError(f"cad-intersection: unknown layout {layout!r}; known: {', '.join(CAD_LAYOUTS)}")


def _nodes(roads: np.ndarray) -> list[tuple[np.ndarray, list[np.ndarray], dict]]:
    """Junctions: (position, outgoing arm directions, {direction: road row})."""
    out = []
    for a in roads[roads[:, 0] == 0]:
        for b in roads[roads[:, 0] == 1]:
            if a[3] <= b[1] <= a[4] and b[3] - 1 <= a[1] <= b[4] + 1:
                p = np.array([b[1], a[1]])
                arms, road_of = [], {}
                for d, r, lo, hi, c in (((1, 0), a, a[3], a[4], p[0]), ((-1, 0), a, a[3], a[4], p[0]),
                                        ((0, 1), b, b[3], b[4], p[1]), ((0, -1), b, b[3], b[4], p[1])):
                    sgn = d[0] + d[1]
                    if (hi - c if sgn > 0 else c - lo) > 60:
                        arms.append(np.array(d, float))
                        road_of[d] = r
                out.append((p, arms, road_of))
    return out


def _route(node: np.ndarray, road_of: dict, d_in: np.ndarray, d_out: np.ndarray, lane: int,
           L_in: float = 140.0, L_out: float = 140.0) -> Path2D:
    """Vehicle path entering the junction from arm ``d_in`` (pointing away from it) and
    leaving along arm ``d_out``, keeping right, in lane ``lane`` (0 = next to the centre)."""
    h0, h1 = -d_in, d_out
    r_in, r_out = road_of[tuple(int(v) for v in d_in)], road_of[tuple(int(v) for v in d_out)]
    off0 = r_in[2] / r_in[5] * (lane + 0.5) if lane < r_in[5] else r_in[2] / r_in[5] * (r_in[5] - 0.5)
    off1 = r_out[2] / r_out[5] * (min(lane, r_out[5] - 1) + 0.5)
    if np.allclose(h0, h1):
        a = node + off0 * _right(h0) - h0 * L_in
        return Path2D(_line(a, a + h0 * (L_in + L_out)))
    if np.allclose(h0, -h1):
        raise SynthError("route: U-turns are not generated")
    X = node + off0 * _right(h0) + off1 * _right(h1)
    left = h0[0] * h1[1] - h0[1] * h1[0] > 0
    r = 10.0 if left else 5.0
    A, B = X - h0 * r, X + h1 * r
    centre = A + h1 * r
    a0 = np.arctan2(*(A - centre)[::-1])
    a1 = np.arctan2(*(B - centre)[::-1])
    da = (a1 - a0 + np.pi) % (2 * np.pi) - np.pi
    ang = a0 + np.linspace(0, da, 60)
    arc = centre + r * np.stack([np.cos(ang), np.sin(ang)], 1)
    pts = np.concatenate([_line(X - h0 * L_in, A)[:-1], arc, _line(B, B + h1 * L_out)[1:]])
    return Path2D(pts)


def _facade(rng: np.random.Generator, seed: int, shop: bool) -> Material:
    brick = rng.random() < 0.45
    if brick:
        color = tuple(np.array([0.62, 0.32, 0.22]) * rng.uniform(0.8, 1.2, 3))
    else:
        color = tuple(np.clip(rng.uniform(0.45, 0.9) * np.array([1.0, 0.95, 0.85]) * rng.uniform(0.85, 1.15, 3), 0, 1))
    return Material(tx.FACADE, color, (rng.uniform(2.9, 3.6), rng.uniform(2.2, 3.6), float(brick), float(shop)), seed)


def _car(rng: np.random.Generator, seed: int, size=(4.4, 1.8, 1.5), color=None, van: bool | None = None) -> FaceSet:
    """A vehicle in its own frame (x forward, z up, base at z=0).

    A car is a body box plus a glass cabin box. With ``van`` (default: 20 % of draws,
    always for height > 2 m) it is a single box with a glass band."""
    color = tuple(color if color is not None else np.clip(rng.choice(
        [[0.75, 0.1, 0.08], [0.1, 0.2, 0.55], [0.85, 0.85, 0.85], [0.12, 0.12, 0.13], [0.5, 0.52, 0.55],
         [0.9, 0.75, 0.1], [0.15, 0.4, 0.2], [0.95, 0.95, 0.95]]) * rng.uniform(0.9, 1.1, 3), 0, 1))
    m = lambda f: Material(tx.CAR, color, (f, 0, 0, 0), seed)  # noqa: E731
    L, W, H = size
    if van is None:
        van = H > 2.0 or rng.random() < 0.2
    if van:
        return box((0, 0), 0.0, size, 0.0, m(0), top=m(3), front=m(1), back=m(2))
    hb = 0.9
    body = box((0, 0), 0.0, (L, W, hb), 0.0, m(0), top=m(3), front=m(1), back=m(2))
    cabin = box((-0.08 * L, 0), hb, (0.55 * L, 0.92 * W, H - hb), 0.0, m(4), top=m(3))
    return FaceSet.concat([body, cabin])


def _truck(rng: np.random.Generator, seed: int) -> FaceSet:
    """Truck in its frame: a cab and a long box trailer with adverts on both sides."""
    cab_col = tuple(rng.uniform(0.2, 0.9, 3))
    cab = _car(rng, seed, size=(2.4, 2.5, 3.0), color=cab_col).transformed(yaw_pose(4.6, 0, 0))
    plain = Material(tx.PLAIN, (0.85, 0.85, 0.85), seed=seed + 1)
    trailer = box((-1.6, 0), 0.6, (9.5, 2.5, 3.4), 0.0, plain, top=plain,
                  sides=(Material(tx.POSTER, seed=seed + 2), Material(tx.POSTER, seed=seed + 3)))
    return FaceSet.concat([cab, trailer])


def _cad_static(rng: np.random.Generator, roads: np.ndarray, seed: int) -> FaceSet:
    parts = [quad((-220, -220, 0), (440, 0, 0), (0, 440, 0), Material(tx.GROUND, seed=seed))]
    rects: list[tuple[float, float, float, float]] = []  # occupied footprints (x0, y0, x1, y1)

    def road_rect(r, pad):
        ax, c, hw, s0, s1 = r[:5]
        return (s0, c - hw - pad, s1, c + hw + pad) if ax == 0 else (c - hw - pad, s0, c + hw + pad, s1)

    def overlaps(a, b):
        return a[0] < b[2] and b[0] < a[2] and a[1] < b[3] and b[1] < a[3]

    road_rects = [road_rect(r, 3.5) for r in roads]
    k = 0
    for r in roads:
        ax, c, hw, s0, s1 = r[:5]
        for side in (-1, 1):
            s = max(s0, -130.0) + rng.uniform(0, 6)
            while s < min(s1, 130.0):
                width = rng.uniform(9, 22)
                depth = rng.uniform(10, 16)
                height = rng.uniform(7, 28) if abs(s) < 70 else rng.uniform(12, 35)
                setback = hw + rng.uniform(3.5, 5.0)
                lat0 = c + side * setback
                lat1 = c + side * (setback + depth)
                a0, a1 = s, s + width
                rect = ((a0, min(lat0, lat1), a1, max(lat0, lat1)) if ax == 0
                        else (min(lat0, lat1), a0, max(lat0, lat1), a1))
                if not any(overlaps(rect, q) for q in road_rects + rects):
                    rects.append(rect)
                    cx, cy = (rect[0] + rect[2]) / 2, (rect[1] + rect[3]) / 2
                    # the box's front (+heading) faces the road
                    yaw = (-np.pi / 2 if side > 0 else np.pi / 2) if ax == 0 else (np.pi if side > 0 else 0.0)
                    bseed = seed * 1000 + k
                    fac = _facade(rng, bseed, shop=rng.random() < 0.6)
                    plain_fac = Material(tx.FACADE, fac.color, fac.prm[:3] + (0.0,), bseed)
                    roof = Material(tx.ROOF, tuple(rng.uniform(0.3, 0.5) * np.ones(3)), seed=bseed)
                    parts.append(box((cx, cy), 0.0, (depth, width, height), yaw, plain_fac, top=roof, front=fac))
                    k += 1
                s += width + rng.uniform(0.0, 4.0)
            # parked cars along the kerb, away from junctions
            s = max(s0, -110.0) + rng.uniform(0, 10)
            while s < min(s1, 110.0):
                near_junction = any(int(r2[0]) != ax and abs(s - r2[1]) < r2[2] + 9 for r2 in roads)
                if not near_junction and rng.random() < 0.55:
                    lat = c + side * (hw - 1.1)
                    yaw = (0.0 if side < 0 else np.pi) if ax == 0 else (np.pi / 2 if side > 0 else -np.pi / 2)
                    x, y = (s, lat) if ax == 0 else (lat, s)
                    parts.append(_car(rng, seed * 1000 + 500 + k).transformed(yaw_pose(x, y, yaw)))
                    k += 1
                s += rng.uniform(5.5, 9.0)
            # poster kiosks and lamp posts on the sidewalk
            s = max(s0, -100.0) + rng.uniform(0, 15)
            while s < min(s1, 100.0):
                lat = c + side * (hw + 1.6)
                x, y = (s, lat) if ax == 0 else (lat, s)
                if not any(int(r2[0]) != ax and abs(s - r2[1]) < r2[2] + 2 for r2 in roads):
                    if rng.random() < 0.5:
                        pm = Material(tx.POSTER, seed=seed * 1000 + 700 + k)
                        pm2 = Material(tx.POSTER, seed=seed * 1000 + 800 + k)
                        yaw = 0.0 if ax == 0 else np.pi / 2
                        parts.append(box((x, y), 0.0, (1.3, 0.35, 2.3), yaw, pm, sides=(pm, pm2),
                                         top=Material(tx.PLAIN, (0.2, 0.3, 0.25), seed=k)))
                    else:
                        parts.append(box((x, y), 0.0, (0.16, 0.16, 5.5), 0.0, Material(tx.PLAIN, (0.25, 0.27, 0.28), seed=k)))
                    k += 1
                s += rng.uniform(8, 16)
    return FaceSet.concat(parts)


def _vehicles_collide(moving: list[MovingObject], margin_m: float = 0.4) -> bool:
    """True if two vehicle bodies come closer than ``margin_m`` at any step.

    Each body is covered by discs along its long axis (cars: 3 discs of 1.1 m; the
    truck, the only object longer than 6 m: 6 discs of 1.35 m)."""
    discs = []
    for m in moving:
        ext = np.ptp(m.faces.origin[:, 0]) if len(m.faces) else 0.0
        offs, r = (np.linspace(-5.5, 5.0, 6), 1.35) if ext > 6.0 else (np.array([-1.5, 0.0, 1.5]), 1.1)
        R, t = m.T_world_obj[:, :2, :2], m.T_world_obj[:, :2, 3]
        discs.append((t[:, None, :] + offs[None, :, None] * R[:, None, :, 0], r))  # [T,k,2]
    for a in range(len(discs)):
        for b in range(a + 1, len(discs)):
            (pa, ra), (pb, rb) = discs[a], discs[b]
            d = np.linalg.norm(pa[:, :, None, :] - pb[:, None, :, :], axis=-1)
            if d.min() < ra + rb + margin_m:
                return True
    return False


def draw_encounter(seed: int, index: int, conf: dict, attempt: int) -> EncounterPlan:
    """Draw one vehicle encounter at a junction of layout ``CAD_LAYOUTS[index % 4]`` (attempt ``attempt``)."""
    rng = np.random.default_rng([seed, index, attempt, 17])
    layout = CAD_LAYOUTS[index % len(CAD_LAYOUTS)]
    roads = _cad_roads(layout)
    n_rob, T, fps = conf["n_robots"], conf["n_frames"], conf["fps"]
    dt = 1.0 / fps
    dur = (T - 1) * dt
    nodes = _nodes(roads)
    node, arms, road_of = nodes[rng.integers(len(nodes))]
    # alternate by index so a suite has both kinds: overlap first then lost (diverge: one vehicle
    # turns away) and no overlap first, then overlap (converge: one turns in ahead of the other)
    scenario = ("diverge", "converge")[(index + attempt // 4) % 2]
    v = rng.uniform(5.0, 9.0) if conf.get("fast", False) else rng.uniform(3.0, 10.0)

    def pick_turn(d_in, allow_straight=True):
        outs = [d for d in arms if not np.allclose(d, d_in) and (allow_straight or not np.allclose(d, -d_in))]
        return outs[int(rng.integers(len(outs)))]

    routes, t_node = [], []
    gap_t = rng.uniform(9.0, 16.0) / v  # follower 9-16 m behind the leader
    t_lead = dur * rng.uniform(0.3, 0.55)
    if scenario == "diverge":
        straight_ok = [d for d in arms if any(np.allclose(-d, e) for e in arms)]
        d_in = straight_ok[int(rng.integers(len(straight_ok)))] if straight_ok else arms[0]
        lead_out = pick_turn(d_in, allow_straight=False)
        fol_out = -d_in if any(np.allclose(-d_in, e) for e in arms) else pick_turn(d_in)
        routes = [_route(node, road_of, d_in, lead_out, 0), _route(node, road_of, d_in, fol_out, 0)]
        t_node = [t_lead, t_lead + gap_t]
    else:
        outs = [d for d in arms if any(np.allclose(-d, e) for e in arms) and any(abs(e @ d) < 0.5 for e in arms)]
        if not outs:
            return draw_encounter(seed, index, conf, attempt + 100)
        # the leader has just crossed straight and drives away; the follower comes from a
        # side road (looking across the junction, not where the leader looks) and turns in
        # behind it: no overlap first, then a lot
        d_out = outs[int(rng.integers(len(outs)))]
        side_in = [d for d in arms if abs(d @ d_out) < 0.5]
        fol_side = side_in[int(rng.integers(len(side_in)))]
        routes = [_route(node, road_of, -d_out, d_out, 0), _route(node, road_of, fol_side, d_out, 0)]
        t_fol = dur * rng.uniform(0.3, 0.55)
        t_node = [t_fol - gap_t, t_fol]
    for k in range(2, n_rob):  # extra vehicles cross the junction on their own routes
        d_in = arms[int(rng.integers(len(arms)))]
        routes.append(_route(node, road_of, d_in, pick_turn(d_in), 0))
        t_node.append(dur * rng.uniform(0.2, 0.8))
    # the follower is never faster than the leader: it must not drive into it
    speeds = [v, v * rng.uniform(0.9, 1.0)] + [v * rng.uniform(0.9, 1.1) for _ in range(2, n_rob)]
    times = np.arange(T) * dt
    T_wc = np.zeros((n_rob, T, 4, 4))
    moving: list[MovingObject] = []
    pitch = np.deg2rad(conf.get("pitch_deg", 3.0))
    cam_h = conf.get("camera_height_m", 1.5)
    for k, (path, tn, sp) in enumerate(zip(routes, t_node, speeds)):
        s_node = path.closest_s(node)
        s = s_node + sp * (times - tn)
        if s.min() < 0 or s.max() > path.length:
            raise SynthError(f"cad-intersection: trajectory of robot {k} leaves its road (speed {sp:.1f} m/s, "
                             f"{T} frames); use fewer frames")
        x, y, h = path.at(s)
        T_wc[k] = [camera_pose(x[t], y[t], cam_h, h[t], pitch) for t in range(T)]
        body = _car(rng, seed * 100 + k, size=(4.4, 1.8, 1.45), van=False)
        T_body = np.stack([yaw_pose(x[t] - 1.0 * np.cos(h[t]), y[t] - 1.0 * np.sin(h[t]), h[t]) for t in range(T)])
        moving.append(MovingObject(body, T_body, owner=k, name=f"vehicle r{k}"))
    # a truck crossing the junction straight, shortly before the leader gets there (it
    # occludes); draws where any two vehicles would touch are rejected below
    straight = [d for d in arms if any(np.allclose(-d, e) for e in arms)] or arms
    d_in = straight[int(rng.integers(len(straight)))]
    tpath = _route(node, road_of, d_in, -d_in if any(np.allclose(-d_in, e) for e in arms) else pick_turn(d_in), 0)
    t_truck = t_node[0] - rng.uniform(1.5, 3.5)
    ts = tpath.closest_s(node) + rng.uniform(4.0, 8.0) * (times - t_truck)
    tx_, ty_, th_ = tpath.at(ts)
    moving.append(MovingObject(_truck(rng, seed * 100 + 50),
                               np.stack([yaw_pose(tx_[t], ty_[t], th_[t]) for t in range(T)]), name="truck"))
    collision = _vehicles_collide(moving)
    W, H = conf["size"]
    f = conf.get("focal_ratio", 0.65) * W
    K = CameraIntrinsics(f, f, (W - 1) / 2, (H - 1) / 2, W, H)
    static = _cad_static(rng, roads, seed * 10 + index)
    meta = {"layout": layout, "scenario": scenario, "speed_mps": [round(float(s), 3) for s in speeds],
            "junction_xy": node.tolist(), "attempt": attempt, "collision": collision}
    return EncounterPlan(name="", world="cad-intersection", static=static, moving=moving,
                         robot_ids=[f"r{k}" for k in range(n_rob)], T_world_cam=T_wc, intrinsics=K,
                         stamps_s=times, ctx=tx.ShadeContext(roads=roads, outdoor=True), meta=meta)

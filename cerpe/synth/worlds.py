"""Seeded encounter worlds: ``cad-intersection`` (vehicles at urban junctions) and
``indoor-team`` (three ground robots in a furnished room).

World frame: x east, y north, z up, metres; the ground is ``z = 0``. Cameras use
OpenCV axes; ``T_world_cam`` is camera-to-world. An :class:`EncounterPlan` holds
everything needed to render an encounter: static faces, moving objects with a
pose per step (other robots' bodies among them), every robot's camera
trajectory, intrinsics, stamps and the shading context.

Trajectories are smooth by construction: vehicles follow lane lines joined by
circular arcs at constant speed; indoor robots drift on Lissajous curves and
turn towards scheduled look-at targets (yaw smoothed with a Gaussian over time).
Each scenario is drawn from a seed; :func:`plan_encounter` re-draws (up to
``max_attempts``) until a quick low-resolution (128 px wide) depth render shows the overlap of
some robot pair rising above 0.3 *and* falling below 0.05 (see
:func:`cerpe.synth.groundtruth.has_transition`).
"""
from __future__ import annotations

import logging
from dataclasses import dataclass, field

import numpy as np

from ..scene import CameraIntrinsics
from . import textures as tx
from .errors import SynthError
from .groundtruth import has_transition, overlap_matrix
from .renderer import FaceSet, Material, box, quad, render

log = logging.getLogger(__name__)

WORLDS = ("cad-intersection", "indoor-team")
CAD_LAYOUTS = ("cross", "t-junction", "offset-cross", "boulevard")


@dataclass
class MovingObject:
    """Faces in the object frame and its pose ``T_world_obj [T,4,4]`` per step.
    ``owner`` is the robot index whose body this is (hidden from its own camera), or -1."""

    faces: FaceSet
    T_world_obj: np.ndarray
    owner: int = -1
    name: str = "object"


@dataclass
class EncounterPlan:
    """Everything needed to render one encounter (no pixels yet)."""

    name: str
    world: str
    static: FaceSet
    moving: list[MovingObject]
    robot_ids: list[str]
    T_world_cam: np.ndarray          # [N,T,4,4]
    intrinsics: CameraIntrinsics
    stamps_s: np.ndarray             # [T]
    ctx: tx.ShadeContext
    meta: dict = field(default_factory=dict)

    @property
    def n_steps(self) -> int:
        return int(self.T_world_cam.shape[1])

    def faces_at(self, t: int, viewer: int | None = None) -> FaceSet:
        """World faces at step ``t``, without the body of robot ``viewer``."""
        parts = [self.static] + [m.faces.transformed(m.T_world_obj[t]) for m in self.moving
                                 if viewer is None or m.owner != viewer]
        return FaceSet.concat(parts)


# --------------------------------------------------------------------------- poses
def yaw_pose(x: float, y: float, yaw: float, z: float = 0.0) -> np.ndarray:
    T = np.eye(4)
    c, s = np.cos(yaw), np.sin(yaw)
    T[:3, :3] = [[c, -s, 0], [s, c, 0], [0, 0, 1]]
    T[:3, 3] = [x, y, z]
    return T


def camera_pose(x: float, y: float, z: float, yaw: float, pitch_down: float = 0.0) -> np.ndarray:
    """``T_world_cam`` of a camera at (x,y,z) looking along heading ``yaw``, tilted down by ``pitch_down``."""
    cp, sp = np.cos(pitch_down), np.sin(pitch_down)
    zc = np.array([cp * np.cos(yaw), cp * np.sin(yaw), -sp])
    xc = np.array([np.sin(yaw), -np.cos(yaw), 0.0])
    yc = np.cross(zc, xc)
    T = np.eye(4)
    T[:3, :3] = np.stack([xc, yc, zc], 1)
    T[:3, 3] = [x, y, z]
    return T


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


# --------------------------------------------------------------------------- cad-intersection
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
    """A vehicle in its own frame (x forward, z up, base at z=0): a car (body box plus
    a glass cabin box) or, with ``van`` (default: 20 % of draws, always for height > 2 m),
    a single box with a glass band."""
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


def _cad_plan(seed: int, index: int, conf: dict, attempt: int) -> EncounterPlan:
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
            return _cad_plan(seed, index, conf, attempt + 100)
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


# --------------------------------------------------------------------------- indoor-team
def _vquad(p0, p1, z0: float, height: float, mat: Material, inset: float = 0.0) -> FaceSet:
    """Vertical rectangle from ``p0`` to ``p1`` (plan view); it faces the right-hand side of p0->p1."""
    p0, p1 = np.asarray(p0, float), np.asarray(p1, float)
    d = p1 - p0
    n = np.array([d[1], -d[0]]) / np.linalg.norm(d)
    o = np.array([*(p0 + n * inset), z0])
    return quad(o, (d[0], d[1], 0.0), (0, 0, height), mat)


def _indoor_static(rng: np.random.Generator, room: tuple[float, float, float], seed: int) -> tuple[FaceSet, list]:
    Wr, Dr, Hr = room
    wall_col = [tuple(np.clip(rng.uniform(0.6, 0.95) * rng.uniform(0.85, 1.1, 3), 0, 1)) for _ in range(4)]
    parts = [
        quad((0, 0, 0), (Wr, 0, 0), (0, Dr, 0), Material(tx.FLOOR, tuple(np.array([0.6, 0.42, 0.25]) * rng.uniform(0.8, 1.2)), seed=seed)),
        quad((0, 0, Hr), (0, Dr, 0), (Wr, 0, 0), Material(tx.CEILING, (0.92, 0.92, 0.9), seed=seed + 1)),
    ]
    # walls, listed so that each faces into the room: (p0, p1) clockwise seen from above
    walls = [((Wr, 0), (0, 0)), ((0, 0), (0, Dr)), ((0, Dr), (Wr, Dr)), ((Wr, Dr), (Wr, 0))]
    for w, (p0, p1) in enumerate(walls):
        parts.append(_vquad(p0, p1, 0, Hr, Material(tx.WALL, wall_col[w], (float(rng.integers(3)), 0, 0, 0), seed + 10 + w)))
    k = 0
    items = []
    for w, (p0, p1) in enumerate(walls):
        p0, p1 = np.asarray(p0, float), np.asarray(p1, float)
        Lw = np.linalg.norm(p1 - p0)
        e = (p1 - p0) / Lw
        n_in = np.array([e[1], -e[0]])
        # posters: some low enough for a 0.2 m camera
        for _ in range(int(rng.integers(3, 6))):
            pw, ph = rng.uniform(0.4, 1.0), rng.uniform(0.5, 1.1)
            a = rng.uniform(0.3, Lw - pw - 0.3)
            z0 = rng.uniform(0.15, 1.0)
            parts.append(_vquad(p0 + e * a, p0 + e * (a + pw), z0, ph, Material(tx.POSTER, seed=seed * 100 + k), inset=0.01))
            k += 1
        # furniture along the wall, in a band of ~1 m
        a = rng.uniform(0.2, 0.8)
        while a < Lw - 0.8:
            kind = rng.choice(["shelf", "table", "boxes", "cabinet", "sofa", "gap"], p=[0.25, 0.15, 0.25, 0.12, 0.1, 0.13])
            width = {"shelf": rng.uniform(0.8, 1.6), "table": rng.uniform(1.0, 1.6), "boxes": rng.uniform(0.6, 1.2),
                     "cabinet": rng.uniform(0.6, 1.2), "sofa": rng.uniform(1.6, 2.2), "gap": rng.uniform(0.4, 1.2)}[kind]
            if a + width > Lw - 0.2:
                break
            mid = p0 + e * (a + width / 2)
            yaw = float(np.arctan2(n_in[1], n_in[0]))  # box front (+heading) faces the room
            wood = Material(tx.WOOD, tuple(np.array([0.55, 0.38, 0.22]) * rng.uniform(0.7, 1.3)), seed=seed * 100 + k)
            if kind == "shelf":
                depth = 0.35
                c = mid + n_in * (depth / 2 + 0.02)
                books = Material(tx.BOOKS, wood.color, seed=seed * 100 + k + 1)
                parts.append(box(c, 0, (depth, width, rng.uniform(1.2, 2.0)), yaw, wood, front=books))
            elif kind == "table":
                depth = 0.8
                c = mid + n_in * (depth / 2 + 0.15)
                parts.append(box(c, 0.71, (depth, width, 0.04), yaw, wood, bottom=True))
                for sx in (-1, 1):
                    for sy in (-1, 1):
                        lc = c + n_in * sx * (depth / 2 - 0.06) + e * sy * (width / 2 - 0.06)
                        parts.append(box(lc, 0, (0.05, 0.05, 0.71), yaw, wood))
                # something on the floor under the table
                if rng.random() < 0.6:
                    bc = c + e * rng.uniform(-0.3, 0.3)
                    parts.append(box(bc, 0, (0.4, 0.5, 0.35), yaw, Material(tx.CARDBOARD, (0.62, 0.45, 0.28), seed=seed * 100 + k + 2)))
            elif kind == "boxes":
                depth = rng.uniform(0.4, 0.6)
                z = 0.0
                for lvl in range(int(rng.integers(1, 4))):
                    hgt = rng.uniform(0.25, 0.5)
                    c = mid + n_in * (depth / 2 + 0.05) + e * rng.uniform(-0.05, 0.05)
                    cb = Material(tx.CARDBOARD, tuple(np.array([0.62, 0.45, 0.28]) * rng.uniform(0.85, 1.15)), seed=seed * 100 + k + 3 + lvl)
                    parts.append(box(c, z, (depth * rng.uniform(0.8, 1.0), width * rng.uniform(0.7, 1.0), hgt),
                                     yaw + rng.uniform(-0.1, 0.1), cb))
                    z += hgt
            elif kind == "cabinet":
                depth = 0.5
                c = mid + n_in * (depth / 2 + 0.02)
                front = Material(tx.POSTER, seed=seed * 100 + k + 4) if rng.random() < 0.3 else wood
                parts.append(box(c, 0.05, (depth, width, rng.uniform(0.7, 1.0)), yaw, wood, front=front))
            elif kind == "sofa":
                depth = 0.9
                c = mid + n_in * (depth / 2 + 0.05)
                cloth = Material(tx.PLAIN, tuple(rng.uniform(0.2, 0.7, 3)), seed=seed * 100 + k + 5)
                parts.append(box(c, 0.08, (depth, width, 0.38), yaw, cloth))
                parts.append(box(mid + n_in * 0.15, 0.08, (0.2, width, 0.85), yaw, cloth))
            items.append(kind)
            k += 10
            a += width + rng.uniform(0.1, 0.6)
    # a rug with a bold pattern in the middle of the room
    rw, rd = rng.uniform(1.5, 2.5), rng.uniform(1.2, 2.0)
    parts.append(quad((Wr / 2 - rw / 2 + rng.uniform(-0.5, 0.5), Dr / 2 - rd / 2 + rng.uniform(-0.5, 0.5), 0.003),
                      (rw, 0, 0), (0, rd, 0), Material(tx.POSTER, seed=seed * 100 + 999)))
    return FaceSet.concat(parts), items


def _smooth(x: np.ndarray, sigma: float) -> np.ndarray:
    from scipy.ndimage import gaussian_filter1d

    return gaussian_filter1d(x, sigma, mode="nearest") if sigma > 0 else x


def _indoor_plan(seed: int, index: int, conf: dict, attempt: int) -> EncounterPlan:
    rng = np.random.default_rng([seed, index, attempt, 29])
    n_rob, T, fps = conf["n_robots"], conf["n_frames"], conf["fps"]
    dt = 1.0 / fps
    times = np.arange(T) * dt
    dur = max(times[-1], dt)
    room = (rng.uniform(7.0, 10.0), rng.uniform(5.5, 7.5), 2.7)
    static, items = _indoor_static(rng, room, seed * 10 + index)
    Wr, Dr, _ = room
    lo, hi = np.array([1.5, 1.5]), np.array([Wr - 1.5, Dr - 1.5])
    # robot centres spread over the free middle of the room
    centres = []
    while len(centres) < n_rob:
        c = rng.uniform(lo + 0.4, hi - 0.4)
        if all(np.linalg.norm(c - q) > 1.2 for q in centres) or rng.random() < 0.02:
            centres.append(c)
    # look-at schedule: alternate "shared" (all look at one spot) and "apart" phases
    wall_pts = lambda: np.array([rng.choice([0.0, Wr]), rng.uniform(0.5, Dr - 0.5)]) if rng.random() < 0.5 \
        else np.array([rng.uniform(0.5, Wr - 0.5), rng.choice([0.0, Dr])])  # noqa: E731
    n_seg = max(3, int(round(dur / rng.uniform(1.4, 2.4))))
    bounds = np.sort(rng.uniform(0.15, 0.85, n_seg - 1)) * dur
    bounds = np.concatenate([[0.0], bounds, [dur + dt]])
    shared_first = bool(rng.integers(2))
    seg_of_t = np.searchsorted(bounds, times, side="right") - 1
    shared_targets = [wall_pts() for _ in range(n_seg)]
    T_wc = np.zeros((n_rob, T, 4, 4))
    moving: list[MovingObject] = []
    sig = max(1.0, 0.35 / dt)
    for k in range(n_rob):
        amp = rng.uniform(0.2, 0.7, 2)
        per = rng.uniform(4.0, 9.0, 2)
        ph = rng.uniform(0, 2 * np.pi, 2)
        p = centres[k][None] + amp * np.sin(2 * np.pi * times[:, None] / per + ph)
        p = np.clip(p, lo, hi)
        yaw_t = np.zeros(T)
        apart_dir = rng.uniform(0, 2 * np.pi)
        for t in range(T):
            sg = seg_of_t[t]
            shared = (sg % 2 == 0) == shared_first
            tgt = shared_targets[sg]
            to_t = np.arctan2(tgt[1] - p[t, 1], tgt[0] - p[t, 0])
            yaw_t[t] = to_t if shared else to_t + np.pi * (0.65 + 0.5 * k / max(n_rob - 1, 1)) * (1 if k % 2 else -1)
        yaw_t = _smooth(np.unwrap(yaw_t), sig)
        T_wc[k] = [camera_pose(p[t, 0] + 0.14 * np.cos(yaw_t[t]), p[t, 1] + 0.14 * np.sin(yaw_t[t]),
                               conf.get("camera_height_m", 0.2), yaw_t[t], np.deg2rad(-2.0)) for t in range(T)]
        colr = tuple(tx.palette(np.array([k / max(n_rob, 1)]), 0.9, 0.9)[0])
        body = box((0, 0), 0.02, (0.32, 0.22, 0.17), 0.0, Material(tx.ROBOT, colr, seed=seed * 100 + k))
        moving.append(MovingObject(body, np.stack([yaw_pose(p[t, 0], p[t, 1], yaw_t[t]) for t in range(T)]),
                                   owner=k, name=f"robot r{k}"))
        del apart_dir
    # one moving object: a cart of boxes pushed back and forth across the room
    a, b = np.array([rng.uniform(1.2, 2.0), rng.uniform(1.2, Dr - 1.2)]), np.array([rng.uniform(Wr - 2.0, Wr - 1.2), rng.uniform(1.2, Dr - 1.2)])
    period = rng.uniform(5.0, 9.0)
    w = 0.5 - 0.5 * np.cos(2 * np.pi * times / period + rng.uniform(0, 2 * np.pi))
    pos = a[None] + w[:, None] * (b - a)[None]
    yaw_c = float(np.arctan2(*(b - a)[::-1]))
    cart = FaceSet.concat([box((0, 0), 0.12, (0.7, 0.45, 0.4), 0.0, Material(tx.CARDBOARD, (0.6, 0.44, 0.27), seed=seed * 100 + 77)),
                           box((0, 0), 0.0, (0.72, 0.47, 0.12), 0.0, Material(tx.PLAIN, (0.1, 0.3, 0.6), seed=3))])
    moving.append(MovingObject(cart, np.stack([yaw_pose(q[0], q[1], yaw_c) for q in pos]), name="cart"))
    W, H = conf["size"]
    f = conf.get("focal_ratio", 0.7) * W
    K = CameraIntrinsics(f, f, (W - 1) / 2, (H - 1) / 2, W, H)
    meta = {"room_m": [round(float(x), 3) for x in room], "furniture": [str(i) for i in items],
            "attempt": attempt, "shared_first": shared_first, "segment_bounds_s": [round(float(x), 3) for x in bounds]}
    return EncounterPlan(name="", world="indoor-team", static=static, moving=moving,
                         robot_ids=[f"r{k}" for k in range(n_rob)], T_world_cam=T_wc, intrinsics=K, stamps_s=times,
                         ctx=tx.ShadeContext(outdoor=False, light_dir=(0.3, 0.5, 0.8)), meta=meta)


# --------------------------------------------------------------------------- entry point
def check_conf(world: str, conf: dict) -> None:
    """Raise :class:`SynthError` for unknown worlds or impossible sizes / counts."""
    if world not in WORLDS:
        raise SynthError(f"unknown world {world!r}; known worlds: {', '.join(WORLDS)}")
    W, H = conf.get("size", (0, 0))
    if not (16 <= int(W) <= 4096 and 16 <= int(H) <= 4096):
        raise SynthError(f"size {W}x{H}: width and height must be between 16 and 4096 pixels")
    if not 2 <= int(conf.get("n_frames", 0)) <= 2000:
        raise SynthError(f"n_frames {conf.get('n_frames')}: must be between 2 and 2000")
    if not 2 <= int(conf.get("n_robots", 0)) <= 6:
        raise SynthError(f"n_robots {conf.get('n_robots')}: must be between 2 and 6")
    if not 0.5 <= float(conf.get("fps", 0)) <= 60:
        raise SynthError(f"fps {conf.get('fps')}: must be between 0.5 and 60")


def plan_encounter(world: str, seed: int, index: int, conf: dict, max_attempts: int = 16) -> EncounterPlan:
    """Draw encounter ``index`` of ``world`` (deterministic in ``seed``, ``index``, ``conf``).

    Re-draws until the quick overlap check at low resolution shows a transition
    (some pair above 0.35 and below 0.03); after ``max_attempts`` the draw with
    the widest overlap range is kept and ``meta["transition_precheck"]`` is False.
    """
    check_conf(world, conf)
    planner = _cad_plan if world == "cad-intersection" else _indoor_plan
    best, best_spread = None, -1.0
    for attempt in range(max_attempts):
        plan = planner(seed, index, conf, attempt)
        if plan.meta.get("collision", False):
            continue  # vehicles would overlap: draw again without rendering anything
        ov = quick_overlap(plan)
        # margins: the final overlap is computed at full resolution and differs a little
        ok = has_transition(ov, high=0.35, low=0.03)
        n = ov.shape[1]
        spread = max(min(ov[:, i, j].max() - 0.3, 0.05 - ov[:, i, j].min()) for i in range(n) for j in range(n) if i != j)
        plan.meta["transition_precheck"] = bool(ok)
        if ok:
            return plan
        if spread > best_spread:
            best, best_spread = plan, spread
    if best is None:
        raise SynthError(f"{world} encounter {index} (seed {seed}): every one of {max_attempts} draws had "
                         f"colliding vehicles; try another seed or fewer frames")
    log.warning("%s encounter %d (seed %d): no overlap transition after %d draws; keeping the best one",
                world, index, seed, max_attempts)
    return best


def quick_overlap(plan: EncounterPlan, width: int = 128) -> np.ndarray:
    """``[T,N,N]`` overlap from depth-only renders at ``width`` pixels (for planning only)."""
    K = plan.intrinsics
    Ks = K.scaled(width / K.width)
    n, T = plan.T_world_cam.shape[:2]
    out = np.zeros((T, n, n))
    for t in range(T):
        depths = [render(plan.faces_at(t, viewer=k), plan.T_world_cam[k, t], Ks, plan.ctx, with_rgb=False).depth_m
                  for k in range(n)]
        out[t] = overlap_matrix(depths, [Ks] * n, list(plan.T_world_cam[:, t]), stride=1)
    return out

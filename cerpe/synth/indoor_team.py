"""The ``indoor-team`` world: ground robots (camera 0.2 m high) in a furnished room.

Robots drift on Lissajous curves and turn towards scheduled look-at targets, all towards one spot
in "shared" phases and away from each other in "apart" ones (yaw smoothed with a Gaussian over
time); a cart of boxes is pushed back and forth. Frames and poses: :mod:`cerpe.synth.plan`.
"""
from __future__ import annotations

import numpy as np

from ..scene import CameraIntrinsics
from . import textures as tx
from .noise import palette
from .plan import EncounterPlan, MovingObject, camera_pose, yaw_pose
from .renderer import FaceSet, Material, box, quad


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


def draw_encounter(seed: int, index: int, conf: dict, attempt: int) -> EncounterPlan:
    """Draw one encounter of ground robots in a furnished room (attempt ``attempt``)."""
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
        colr = tuple(palette(np.array([k / max(n_rob, 1)]), 0.9, 0.9)[0])
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

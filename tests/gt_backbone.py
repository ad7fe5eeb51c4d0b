"""TEST DOUBLES (tests only): a procedural world and plug-ins that read its ground truth.

Nothing here is a model. :class:`GTBackbone` returns the world's true camera
poses, expressed in a fresh arbitrary frame at every call and multiplied by an
unknown scale factor (as a real up-to-scale backbone would), with optional
noise; :class:`OverlapDescriptor` returns vectors whose cosine similarity between
robots follows a prescribed schedule; :class:`SensorDepthDouble` returns the
world's metric depth with optional bias, noise and outliers. Views are looked up
by the key the algorithm gives them: ``(robot_id, step)`` for own frames,
``(robot_id, step, "jpeg")`` for received images (they arrive JPEG-decoded, so
pixels cannot identify them).
"""
from __future__ import annotations

import zlib
from dataclasses import dataclass, field
from typing import Callable, Hashable, Sequence

import numpy as np

from cerpe.geometry import make_se3, random_se3, se3_inverse, so3_exp
from cerpe.protocols import BackboneOutput, FrameContext, Registration, View
from cerpe.scene import CameraIntrinsics, Encounter, RobotStream

WIDTH, HEIGHT = 32, 24


def _key_rng(seed: int, key: Hashable) -> np.random.Generator:
    return np.random.default_rng([seed, zlib.crc32(repr(key).encode())])


@dataclass
class World:
    """A small generated scene.

    Attributes:
        robot_ids: ``N`` names.
        T_world_cam: ``[N,T,4,4]`` camera-to-world poses (OpenCV axes, y down).
        points_w: ``[P,3]`` scene points.
        intrinsics: one tiny pinhole camera shared by all robots.
        similarity: ``[T,N,N]`` target descriptor cosine between robots.
        images: ``[N][T]`` tiny ``uint8`` textures (content irrelevant to the doubles).
        depth_m: ``[N][T]`` ``[H,W]`` z-buffer depth of the points (0 = no point).
    """

    robot_ids: list[str]
    T_world_cam: np.ndarray
    points_w: np.ndarray
    intrinsics: CameraIntrinsics
    similarity: np.ndarray
    images: list[list[np.ndarray]] = field(default_factory=list)
    depth_m: list[list[np.ndarray]] = field(default_factory=list)

    @property
    def n_steps(self) -> int:
        return self.T_world_cam.shape[1]

    def index(self, robot_id: str) -> int:
        return self.robot_ids.index(robot_id)

    def pose(self, key: Hashable) -> np.ndarray:
        rid, t = key[:2]  # own frames (robot, step); received JPEGs (robot, step, "jpeg")
        return self.T_world_cam[self.index(rid), int(t)]

    def depth(self, key: Hashable) -> np.ndarray:
        rid, t = key[:2]
        return self.depth_m[self.index(rid)][int(t)]

    def gt_T_cj_ci(self, t: int, i: int, j: int) -> np.ndarray:
        return se3_inverse(self.T_world_cam[j, t]) @ self.T_world_cam[i, t]

    def gt_odometry(self, i: int, t: int) -> np.ndarray:
        """``X_i^t`` as CERPE defines it: identity at step 0."""
        return se3_inverse(self.T_world_cam[i, 0]) @ self.T_world_cam[i, t]

    def to_encounter(self, name: str = "gt-world") -> Encounter:
        robots = [RobotStream(robot_id=r, intrinsics=self.intrinsics, stamps_s=0.1 * np.arange(self.n_steps),
                              images=self.images[a], T_world_cam=self.T_world_cam[a], depth=self.depth_m[a])
                  for a, r in enumerate(self.robot_ids)]
        return Encounter(name, robots)


def _render_depth(T_world_cam: np.ndarray, pts_w: np.ndarray, K: CameraIntrinsics) -> np.ndarray:
    T_cam_world = se3_inverse(T_world_cam)
    p = pts_w @ T_cam_world[:3, :3].T + T_cam_world[:3, 3]
    z = p[:, 2]
    keep = z > 0.2
    p, z = p[keep], z[keep]
    u = np.floor(K.fx * p[:, 0] / z + K.cx + 0.5).astype(int)
    v = np.floor(K.fy * p[:, 1] / z + K.cy + 0.5).astype(int)
    inside = (u >= 0) & (u < K.width) & (v >= 0) & (v < K.height)
    u, v, z = u[inside], v[inside], z[inside]
    depth = np.full((K.height, K.width), np.inf)
    np.minimum.at(depth, (v, u), z)
    depth[~np.isfinite(depth)] = 0.0
    return depth.astype(np.float32)


def make_world(n_robots: int = 2, n_steps: int = 40, seed: int = 0,
               windows: dict[tuple[int, int], Sequence[tuple[int, int]]] | None = None,
               open_sim: float = 0.6, closed_sim: float = 0.05, n_points: int = 6000) -> World:
    """Smooth trajectories in a field of random points, with an overlap schedule.

    Args:
        windows: per unordered robot pair ``(a, b)`` with ``a < b``, half-open step
            ranges ``[start, stop)`` where the pair "overlaps" (descriptor cosine
            ``open_sim``; ``closed_sim`` otherwise). Default: steps 5-9 and 25-29
            for every pair.
    """
    rng = np.random.default_rng(seed)
    ts = np.arange(n_steps) * 0.1
    T = np.empty((n_robots, n_steps, 4, 4))
    for a in range(n_robots):
        ang = 2 * np.pi * a / n_robots
        start = np.array([8 * np.cos(ang), 0.0, 8 * np.sin(ang)])
        heading0 = ang + np.pi + rng.uniform(-0.4, 0.4)  # roughly towards the centre
        speed, yaw_rate = rng.uniform(2.0, 5.0), rng.uniform(-0.3, 0.3)
        pos = start.copy()
        for k, t in enumerate(ts):
            yaw = heading0 + yaw_rate * t + 0.05 * np.sin(3 * t + a)
            # Camera axis z_cam = (cos yaw, 0, sin yaw) in the world (y down): R = rot_y(pi/2 - yaw).
            R = so3_exp(np.array([0.0, np.pi / 2 - yaw, 0.0])) @ so3_exp(
                np.array([0.02 * np.sin(2 * t + a), 0.0, 0.01 * np.cos(t)]))
            if k > 0:
                pos = pos + 0.1 * speed * np.array([np.cos(yaw), 0.0, np.sin(yaw)]) \
                    + np.array([0.0, 0.01 * np.sin(5 * t), 0.0])
            T[a, k] = make_se3(R, pos)
    pts = np.column_stack([rng.uniform(-40, 40, n_points), rng.uniform(-4, 1.6, n_points),
                           rng.uniform(-40, 40, n_points)])
    return world_from_poses(T, pts, seed, windows, open_sim, closed_sim)


def world_from_poses(T: np.ndarray, pts: np.ndarray, seed: int = 0,
                     windows: dict[tuple[int, int], Sequence[tuple[int, int]]] | None = None,
                     open_sim: float = 0.6, closed_sim: float = 0.05) -> World:
    """A :class:`World` of the given ``[N,T,4,4]`` camera poses and points (images, depth, schedule)."""
    n_robots, n_steps = T.shape[:2]
    K = CameraIntrinsics(fx=20.0, fy=20.0, cx=(WIDTH - 1) / 2, cy=(HEIGHT - 1) / 2, width=WIDTH, height=HEIGHT)
    if windows is None:
        windows = {(a, b): [(5, 10), (25, 30)] for a in range(n_robots) for b in range(a + 1, n_robots)}
    sim = np.full((n_steps, n_robots, n_robots), closed_sim)
    for (a, b), ranges in windows.items():
        for lo, hi in ranges:
            sim[lo:hi, a, b] = sim[lo:hi, b, a] = open_sim
    for a in range(n_robots):
        sim[:, a, a] = 1.0
    ids = [f"r{a}" for a in range(n_robots)]
    images = [[_key_rng(seed, (r, t)).integers(0, 256, (HEIGHT, WIDTH, 3), dtype=np.uint8)
               for t in range(n_steps)] for r in ids]
    depth = [[_render_depth(T[a, t], pts, K) for t in range(n_steps)] for a in range(n_robots)]
    return World(ids, T, pts, K, sim, images, depth)


def make_follow_world(n_steps: int = 30, delay: int = 15, seed: int = 0) -> World:
    """Two robots on one path: r1 drives where r0 drove ``delay`` steps earlier (0.3 m to the side,
    turned 0.1 rad), so r1 at step ``t`` sees what r0 saw at ``t - delay``. No overlap windows: their
    descriptors never match at one step (give :class:`OverlapDescriptor` ``places`` for the revisits)."""
    lead = make_world(1, n_steps + delay, seed=seed, windows={})
    side = make_se3(so3_exp(np.array([0.0, 0.1, 0.0])), np.array([0.3, 0.0, 0.0]))
    T = np.stack([lead.T_world_cam[0, delay:], lead.T_world_cam[0, :n_steps] @ side])
    return world_from_poses(T, lead.points_w, seed, windows={})


class GTBackbone:
    """Ground-truth "backbone": true poses in a random frame, times an unknown scale.

    Every call draws a new frame ``T_frame_world`` and a new unit (backbone units
    per metre, log-uniform in ``unit_range``), so an algorithm that mixes poses
    of different passes or forgets the scale gets visibly wrong answers.

    Args:
        rot_noise_rad, trans_noise: per-view Gaussian noise on the returned poses
            (radians; metres before scaling).
        invalid_keys: views reported as not placed.
        invalid: optional ``(current_key, view_key) -> bool``; True reports the view
            as not placed in a pass whose first (current) view is ``current_key``.
        claim_metric: set ``BackboneOutput.metric_unit`` (true only when ``unit_range``
            is ``(1, 1)``; other units make a backbone that claims metres wrongly).
        register: optional ``(own_key, collaborator_key) -> inliers``; > 0 registers
            the collaborator view (key ``(robot, step, "jpeg")``) against that own
            view of the pass (``BackboneOutput.registrations``, its true pose in the
            own camera times the unit), most inliers first. None: no registrations
            (the algorithm then uses ``T_frame_cam``, as with VGGT).
        perturb: optional ``(current_key, via_key, view_key) -> [4,4] or None``: a
            wrong placement injected on the right of the view's true pose (metres);
            ``via_key`` is None for ``T_frame_cam`` and the own view for a registration.
        support: optional ``(current_key, view_key) -> int``: ``BackboneOutput.support`` of
            each placed view (None: left unknown, -1).
    """

    def __init__(self, world: World, unit_range: tuple[float, float] = (0.2, 5.0), rot_noise_rad: float = 0.0,
                 trans_noise: float = 0.0, invalid_keys: Sequence[Hashable] = (),
                 invalid: Callable[[Hashable, Hashable], bool] | None = None, seed: int = 0,
                 claim_metric: bool = False, register: Callable[[Hashable, Hashable], int] | None = None,
                 perturb: Callable[[Hashable, Hashable | None, Hashable], np.ndarray | None] | None = None,
                 support: Callable[[Hashable, Hashable], int] | None = None) -> None:
        self.world = world
        self.support = support
        self.register, self.perturb = register, perturb
        self.claim_metric = claim_metric
        self.unit_range = unit_range
        self.rot_noise_rad = rot_noise_rad
        self.trans_noise = trans_noise
        self.invalid_keys = set(invalid_keys)
        self.invalid = invalid
        self.rng = np.random.default_rng(seed)
        self.calls: list[list[Hashable]] = []

    def infer(self, views: Sequence[View]) -> BackboneOutput:
        self.calls.append([v.key for v in views])
        unit = float(np.exp(self.rng.uniform(*np.log(self.unit_range))))
        T_frame_world = random_se3(self.rng, max_translation=50.0)
        S = len(views)
        T = np.full((S, 4, 4), np.nan)
        valid = np.zeros(S, bool)
        depth, conf, reasons = [], [], []
        for s, v in enumerate(views):
            D = self.world.depth(v.key) * unit
            depth.append(D.astype(np.float32))
            conf.append((D > 0).astype(np.float32))
            if v.key in self.invalid_keys or (self.invalid is not None and self.invalid(views[0].key, v.key)):
                reasons.append("test double: marked invalid")
                continue
            Ts = T_frame_world @ self._pose(views[0].key, None, v.key)
            if self.rot_noise_rad or self.trans_noise:
                Ts = Ts @ make_se3(so3_exp(self.rng.normal(0, self.rot_noise_rad, 3)),
                                   self.rng.normal(0, self.trans_noise, 3))
            Ts[:3, 3] *= unit
            T[s], valid[s] = Ts, True
            reasons.append("")
        support = [] if self.support is None else \
            [int(self.support(views[0].key, v.key)) if valid[s] else -1 for s, v in enumerate(views)]
        return BackboneOutput(T, valid, depth, conf, [v.intrinsics for v in views], reasons,
                              metric_unit=self.claim_metric, registrations=self._registrations(views, unit),
                              support=support)

    def _pose(self, current: Hashable, via: Hashable | None, key: Hashable) -> np.ndarray:
        P = None if self.perturb is None else self.perturb(current, via, key)
        T = self.world.pose(key)
        return T if P is None else T @ P

    def _registrations(self, views: Sequence[View], unit: float) -> dict[int, list[Registration]]:
        if self.register is None:
            return {}
        me, out = views[0].key[0], {}
        own = [s for s, v in enumerate(views) if len(v.key) == 2 and v.key[0] == me]
        for k, v in enumerate(views):
            if len(v.key) != 3:
                continue
            regs = []
            for s in own:
                n = int(self.register(views[s].key, v.key))
                if n > 0:
                    T = se3_inverse(self.world.pose(views[s].key)) @ self._pose(views[0].key, views[s].key, v.key)
                    T[:3, 3] *= unit
                    regs.append(Registration(s, T, n, 2 * n))
            if regs:
                out[k] = sorted(regs, key=lambda r: -r.inliers)
        return out


class OverlapDescriptor:
    """Descriptors whose cross-robot cosine equals ``world.similarity[t]`` at one step.

    ``d(a,t) = [sqrt(beta) e_a(t), sqrt(gamma) u_a, sqrt(1-beta-gamma) B_g(t) L_t[a]]``:
    ``e_a(t)`` rotates slowly in two dimensions private to robot a (own-view change
    over time, which drives the keyframe rule), ``u_a`` is a constant direction
    private to robot a, and ``L_t`` factorises the Gram matrix ``similarity[t] /
    (1 - beta - gamma)`` (eigenvalues clipped when it is not PSD), placed in a block
    of dimensions of its own for each segment ``g(t)`` of steps with one similarity
    matrix. So within a segment the own cosine over a gap ``g`` is
    ``beta cos(omega g) + 1 - beta`` and robots a, b at steps s, t of the same segment
    have cosine ``similarity[t, a, b]`` (a keyframe of an overlap window scores as
    the window did), while across segments they have cosine 0 (what robot a saw
    during an overlap window is not what robot b sees later).

    ``places`` maps own-frame keys ``(robot, step)`` to a place name: those views'
    last part is one direction per place instead, so views of one place (of any
    robots, at any steps) have cosine ``1 - beta - gamma`` and nothing else in
    common (a robot that sees later what another saw earlier). Keys in
    ``zero_keys`` get an all-zero descriptor (a blank image).
    """

    def __init__(self, world: World, beta: float = 0.3, omega: float = 0.3,
                 thresholds: dict[str, float] | None = None, zero_keys: Sequence[Hashable] = (),
                 gamma: float = 0.05, places: dict[tuple[str, int], str] | None = None) -> None:
        n, T = len(world.robot_ids), world.n_steps
        self.world = world
        self.thresholds = dict(thresholds or {})
        self.zero_keys = set(zero_keys)
        self.places = dict(places or {})
        segment = np.zeros(T, int)
        for t in range(1, T):
            segment[t] = segment[t - 1] + int(not np.array_equal(world.similarity[t], world.similarity[t - 1]))
        names = sorted(set(self.places.values()))
        base = 3 * n + n * (segment[-1] + 1)
        self.dim = base + len(names)
        shared = 1.0 - beta - gamma
        self.table = np.zeros((n, T, self.dim), np.float32)
        for t in range(T):
            G = np.clip(world.similarity[t] / shared, -0.999, 0.999)
            np.fill_diagonal(G, 1.0)
            w, V = np.linalg.eigh(G)
            L = V * np.sqrt(np.clip(w, 1e-9, None))
            L /= np.linalg.norm(L, axis=1, keepdims=True)
            block = 3 * n + n * segment[t]
            for a, rid in enumerate(world.robot_ids):
                d = np.zeros(self.dim)
                d[2 * a:2 * a + 2] = np.sqrt(beta) * np.array([np.cos(omega * t), np.sin(omega * t)])
                d[2 * n + a] = np.sqrt(gamma)
                place = self.places.get((rid, t))
                if place is None:
                    d[block:block + n] = np.sqrt(shared) * L[a]
                else:
                    d[base + names.index(place)] = np.sqrt(shared)
                self.table[a, t] = d / np.linalg.norm(d)

    def describe(self, view: View) -> np.ndarray:
        if view.key in self.zero_keys:
            return np.zeros(self.dim, np.float32)
        rid, t = view.key[:2]
        return self.table[self.world.index(rid), int(t)].copy()


class SensorDepthDouble:
    """Metric depth from the frame context (the world's exact depth), optionally corrupted.

    Args:
        bias_sigma: per-frame multiplicative bias ``1 + bias_sigma * z`` with
            ``z ~ N(0,1)`` drawn from the view key (the median cannot remove it).
        pixel_sigma: per-pixel log-normal noise.
        outlier_frac: fraction of valid pixels replaced by uniform 0.1..100 m.
        none_keys: frames for which the source has nothing.
    """

    name = "sensor-double"
    rel_sigma = 0.0  # MetricDepthSource.rel_sigma: as the sensor simulation reports (bias_sigma aside)

    def __init__(self, bias_sigma: float = 0.0, pixel_sigma: float = 0.0, outlier_frac: float = 0.0,
                 none_keys: Sequence[Hashable] = (), seed: int = 0) -> None:
        self.bias_sigma, self.pixel_sigma, self.outlier_frac = bias_sigma, pixel_sigma, outlier_frac
        self.none_keys = set(none_keys)
        self.seed = seed
        self.calls = 0

    def depth_m(self, view: View, frame: FrameContext) -> np.ndarray | None:
        self.calls += 1
        if view.key in self.none_keys or frame.sensor_depth_m is None:
            return None
        d = np.asarray(frame.sensor_depth_m, np.float64).copy()
        rng = _key_rng(self.seed, view.key)
        d *= 1.0 + self.bias_sigma * rng.normal()
        valid = d > 0
        if self.pixel_sigma:
            d[valid] *= np.exp(self.pixel_sigma * rng.normal(size=int(valid.sum())))
        if self.outlier_frac:
            idx = np.flatnonzero(valid)
            pick = rng.choice(idx, int(self.outlier_frac * idx.size), replace=False)
            d.flat[pick] = rng.uniform(0.1, 100.0, pick.size)
        return d.astype(np.float32)

"""Robots online by capture stamps, each at its own pace (test doubles, each node in a thread over its own
Zenoh session on loopback).

One timeline, real time (about 22 s), two robots circling the same points:

* r0 takes frames at 15 Hz from 0 s to 21 s; r1 at 5 Hz, with a clock 0.5 s ahead and a joint pass
  slower than its frame period (it drops frames);
* r1 joins 10 s late, is killed at 13 s (its session ends without a bye), restarts at 14 s (a new
  session, its odometry from identity again), and its camera stalls from 16 s to 19 s.

Checked: nothing hangs or raises; each event is counted once where it should be (r0: the clock offset,
the lost session, the restart, a peer pose too far during the stall; r1: dropped frames, the stall);
estimates stop and resume with each, and r0's direct estimates equal the ground truth at r0's own
stamps (r1's view moved by r1's motion between the two captures, r1's stamps mapped by the offset).
"""
from __future__ import annotations

import threading
import time
from collections import Counter

import numpy as np
import pytest

zenoh = pytest.importorskip("zenoh")

from cerpe.algorithm import AlgorithmConfig, RobotAgent  # noqa: E402
from cerpe.geometry import make_se3, rotation_angle, se3_inverse  # noqa: E402
from cerpe.online.clock import StampClock  # noqa: E402
from cerpe.online.node import RobotNode  # noqa: E402
from cerpe.online.sources import Frame, StallWatch  # noqa: E402
from cerpe.online.zenoh_link import ZenohLink  # noqa: E402
from cerpe.protocols import FrameContext  # noqa: E402
from gt_backbone import GTBackbone, OverlapDescriptor, SensorDepthDouble, world_from_poses  # noqa: E402
from test_online_zenoh_link import endpoint, free_ports  # noqa: E402

CFG = AlgorithmConfig().override({"scale.min_pixels": 20})
RATES = {"r0": 15.0, "r1": 5.0}
OFFSET = {"r0": 0.0, "r1": 0.5}  # r1's clock is 0.5 s ahead
END_S = 21.0


def T_world_cam(robot: int, time_s: float) -> np.ndarray:
    """Robots on a circle of 8 m around the points, looking at the centre (OpenCV axes, y down)."""
    phi = (0.0 if robot == 0 else 0.5) + 0.08 * time_s
    pos = np.array([8 * np.cos(phi), 0.0, 8 * np.sin(phi)])
    z = -pos / np.linalg.norm(pos)
    x = np.cross(np.array([0.0, 1.0, 0.0]), z)
    return make_se3(np.column_stack([x, np.array([0.0, 1.0, 0.0]), z]), pos)


def make_world():
    rng = np.random.default_rng(0)
    n = int(END_S * RATES["r0"]) + 2
    T = np.stack([[T_world_cam(a, k / RATES[r]) for k in range(n)] for a, r in enumerate(("r0", "r1"))])
    pts = np.column_stack([rng.uniform(-4, 4, 3000), rng.uniform(-3, 1.5, 3000), rng.uniform(-4, 4, 3000)])
    return world_from_poses(T, pts, seed=1, windows={(0, 1): [(0, n)]})


class WallSource:
    """Robot ``a``'s frames of the world: frame k (time k / rate) is due at wall ``w0 + k / rate``, stamped
    ``k / rate + offset``; it plays from ``begin_s`` to ``end_s`` (wall, from ``w0``), none during ``stall``;
    always the newest frame due (the frames overtaken are counted)."""

    def __init__(self, world, robot: str, w0: float, begin_s: float, end_s: float, stall=(None, None)):
        self.world, self.robot, self.w0 = world, robot, w0
        self.rate, self.offset = RATES[robot], OFFSET[robot]
        self.begin_s, self.end_s, self.stall = begin_s, end_s, stall
        self.clock, self.stalls = StampClock(), StallWatch(2.0)
        self.stats = Counter()
        self._stop = threading.Event()

    def stop(self):
        self._stop.set()

    def frames(self):
        a = self.world.index(self.robot)
        last = int(np.ceil(self.begin_s * self.rate)) - 1
        while not self._stop.is_set():
            now = time.time() - self.w0
            if now >= self.end_s:
                return
            if self.stall[0] is not None and self.stall[0] <= now < self.stall[1]:
                time.sleep(0.02)
                continue
            k = int(now * self.rate)
            if k <= last:
                time.sleep(max(0.0, (last + 1) / self.rate - now))
                continue
            dropped, last = k - last - 1, k
            self.stats["input:frame-dropped"] += dropped
            stamp = k / self.rate + self.offset
            self.clock.note(stamp, self.w0 + k / self.rate)  # when the camera gave it
            degr = ("input:frame-dropped",) * dropped + tuple(self.stalls.check(stamp))
            yield Frame(self.world.images[a][k], FrameContext(self.robot, k, self.world.intrinsics,
                                                              self.world.depth_m[a][k], 0),
                        stamp, self.w0 + k / self.rate, None, degr)


class Slow(GTBackbone):
    def infer(self, views):
        time.sleep(0.25)
        return super().infer(views)


def node_of(world, robot, port_of, backbone):
    k = world.index(robot)
    link = ZenohLink(robot, world.robot_ids, {"team": "stamps", "multicast_scouting": False, "sync": "stamps",
                                              "listen": [endpoint(port_of[robot])] if robot == "r0" else [],
                                              "connect": [] if robot == "r0" else [endpoint(port_of["r0"])]})
    agent = RobotAgent(robot, k, CFG, OverlapDescriptor(make_world.world), backbone, SensorDepthDouble())
    return RobotNode(agent, link, world.robot_ids, conf={"wait_s": 0.3, "linger_s": 0.5, "ros": {"key_format": "off"}})


def test_peers_at_their_own_pace_join_late_die_restart_and_stall():
    world = make_world.world = make_world()
    (port,) = free_ports(1)
    ports = {"r0": port}
    w0 = time.time() + 1.0  # the sessions open first
    out, errors = {}, []

    def run(name, node, source, kill=False):
        try:
            out[name] = (list(node.run_stamps(source)), node.report())
            if kill:  # the process dies: its session ends without a bye
                node.link.session.close()
            else:
                node.close()
        except BaseException as exc:  # noqa: BLE001 -- re-raised in the test thread
            errors.append((name, exc))

    def r1_life():
        time.sleep(max(0.0, w0 + 10.0 - time.time()))
        first = node_of(world, "r1", ports, Slow(world, seed=3))
        run("r1a", first, WallSource(world, "r1", w0, 10.0, 13.0), kill=True)
        time.sleep(max(0.0, w0 + 14.0 - time.time()))
        again = node_of(world, "r1", ports, Slow(world, seed=4))
        run("r1b", again, WallSource(world, "r1", w0, 14.0, END_S, stall=(16.0, 19.0)))

    r0 = node_of(world, "r0", ports, GTBackbone(world, seed=2))
    threads = [threading.Thread(target=run, args=("r0", r0, WallSource(world, "r0", w0, 0.0, END_S)), daemon=True),
               threading.Thread(target=r1_life, daemon=True)]
    for th in threads:
        th.start()
    for th in threads:
        th.join(60)
    assert not any(th.is_alive() for th in threads), "a node hung"
    assert not errors, errors

    res0, rep0 = out["r0"]
    stamp = np.array([r.robots[0].stamp_s for r in res0])
    degr = [Counter(r.robots[0].degradations) for r in res0]
    pairs = [r.pairs[0] for r in res0]
    total = sum(degr, Counter())
    # r1 joined at 10 s: nothing about it before, 'peer-absent'
    assert all(p.source == "none" and p.reason.startswith("peer-absent") for p, s in zip(pairs, stamp) if s < 9.9)
    assert total["link:clock-offset"] == 2  # once per session of r1
    assert total["net:peer-lost"] == 1 and total["net:peer-restarted"] == 1
    assert total["pose:too-far"] >= 10  # r1's camera stalled 3 s: no pose of it near r0's frames
    for lo, hi in ((10.5, 13.0), (14.5, 16.0), (19.5, END_S)):  # estimates resume after each event
        got = [p for p, s in zip(pairs, stamp) if lo <= s < hi and p.source == "direct"]
        assert len(got) >= 3, (lo, hi, len(got))
    quiet = 16.0 + CFG.stamps.max_extrapolation_s  # r1's last frame (r0's clock), as far as its pose is extrapolated
    assert not any(p.source != "none" for p, s in zip(pairs, stamp) if quiet + 0.1 <= s < 19.0)  # stalled: silent
    err_rot, err_pos = [], []
    for p, s in zip(pairs, stamp):
        if p.source == "direct":
            G = se3_inverse(T_world_cam(1, s)) @ T_world_cam(0, s)
            E = se3_inverse(G) @ p.T_cj_ci
            err_rot.append(rotation_angle(E[:3, :3]))
            err_pos.append(np.linalg.norm(E[:3, 3]))
    print(f"r0: {len(res0)} frames, {len(err_rot)} direct estimates, median error {np.median(err_rot):.4f} rad "
          f"{np.median(err_pos):.3f} m; counted {dict(total)}; latency median {rep0['latency_median_s']:.3f} s "
          f"p90 {rep0['latency_p90_s']:.3f} s; peer poses {rep0['peer_poses']}")
    assert np.median(err_rot) < 0.01 and np.median(err_pos) < 0.05, (np.median(err_rot), np.median(err_pos))
    assert rep0["clock_offsets_s"]["r1"] == pytest.approx(0.5, abs=0.05)
    assert [e[1:] for e in rep0["peer_events"]] == [["r1", "up"], ["r1", "gone"], ["r1", "restarted"]] or \
        [e[1:] for e in rep0["peer_events"]] == [["r1", "up"], ["r1", "restarted"]]
    # r1: slower than its camera, it drops frames (counted on the frame it takes), and its camera stalled
    r1_total = sum((Counter(r.robots[0].degradations) for r in out["r1a"][0] + out["r1b"][0]), Counter())
    print(f"r1: {len(out['r1a'][0])} frames before the kill, {len(out['r1b'][0])} after the restart, "
          f"{sum(p.source == 'direct' for r in out['r1a'][0] + out['r1b'][0] for p in r.pairs)} direct estimates; "
          f"counted {dict(r1_total)}; clock offset of r0 {out['r1b'][1]['clock_offsets_s']}; "
          f"peer events at r0 {[e[1:] for e in rep0['peer_events']]}")
    assert r1_total["input:frame-dropped"] > 0 and r1_total["input:stall"] == 1
    assert out["r1b"][1]["n_steps"] > 0 and any(p.source == "direct" for r in out["r1b"][0] for p in r.pairs)

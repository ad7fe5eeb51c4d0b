"""cerpe.online: robot nodes in threads of this process, each over its own Zenoh session, against the Team.

Every node has a :class:`ZenohLink` on an explicit tcp/127.0.0.1 endpoint on a free
port (multicast scouting off: tests never need multicast); robot k dials the
robots before it. The key test: with no loss, every robot's per-step relative
poses, gate scores, sources, reasons, bytes and degradations equal what
:class:`cerpe.algorithm.Team` produces for the same encounter (GT test-double
backbone, tests/gt_backbone.py). Each node has its own backbone instance, which
draws other random frames and units than the Team's shared one: poses agree to
floating-point precision, not bit for bit. The real ``cerpe online`` command in
robot processes is tested in tests/test_online_cli.py.
"""
from __future__ import annotations

import dataclasses
import json
import threading
import time
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

zenoh = pytest.importorskip("zenoh")

from cerpe.algorithm import AlgorithmConfig, RobotAgent, Team  # noqa: E402
from cerpe.algorithm.direct import SHARED_VIA  # noqa: E402
from cerpe.config import ConfigError  # noqa: E402
from cerpe.geometry import se3_to_tq_xyzw  # noqa: E402
from cerpe.online import ros  # noqa: E402
from cerpe.online.cli import run_online  # noqa: E402
from cerpe.online.node import OnlineError, RobotNode  # noqa: E402
from cerpe.online.zenoh_link import ZenohLink  # noqa: E402
from cerpe.protocols import FrameContext  # noqa: E402
from cerpe.scene import Setting  # noqa: E402
from gt_backbone import GTBackbone, OverlapDescriptor, SensorDepthDouble, make_world  # noqa: E402
from test_online_zenoh_link import endpoint, free_ports  # noqa: E402

CFG = AlgorithmConfig().override({"scale.min_pixels": 20})
FAST = {"step_timeout_s": 5.0, "connect_timeout_s": 10.0, "linger_s": 3.0, "ros": {"key_format": "off"}}


def link_confs(robots, team="online", ports=None) -> dict[str, dict]:
    """Robot k listens on its own port and dials the robots before it; no multicast."""
    ports = ports or dict(zip(robots, free_ports(len(robots))))
    return {r: {"team": team, "multicast_scouting": False, "listen": [endpoint(ports[r])],
                "connect": [endpoint(ports[q]) for q in robots[:k]]} for k, r in enumerate(robots)}


def frames(world, rid: str, n_steps: int | None = None):
    enc = world.to_encounter()
    r = enc.robots[enc.robot_ids.index(rid)]
    for t in range(enc.n_steps if n_steps is None else n_steps):
        yield r.image(t), FrameContext(rid, t, r.intrinsics, r.depth_m(t), 0), float(r.stamps_s[t])


def make_node(world, rid, lconf, conf=None, backbone=None, config=None):
    agent = RobotAgent(rid, world.index(rid), config or CFG, OverlapDescriptor(world),
                       backbone or GTBackbone(world, seed=7),
                       SensorDepthDouble())
    return RobotNode(agent, ZenohLink(rid, world.robot_ids, lconf), world.robot_ids, conf={**FAST, **(conf or {})})


def make_nodes(world, conf=None):
    confs = link_confs(world.robot_ids)
    return {r: make_node(world, r, confs[r], conf) for r in world.robot_ids}


def run_threads(targets: dict) -> dict:
    """Run ``name -> callable`` in threads; returns name -> result; re-raises the first error."""
    results, errors = {}, {}

    def wrap(name, fn):
        try:
            results[name] = fn()
        except BaseException as exc:  # noqa: BLE001 -- re-raised in the test thread
            errors[name] = exc

    ths = [threading.Thread(target=wrap, args=(k, f), daemon=True) for k, f in targets.items()]
    for th in ths:
        th.start()
    for th in ths:
        th.join(90)
    assert not any(th.is_alive() for th in ths), "a node hung"
    if errors:
        raise next(iter(errors.values()))
    return results


def node_job(node, world, rid, n_steps=None, close=True):
    def job():
        try:
            return list(node.run(frames(world, rid, n_steps)))
        finally:
            if close:
                node.close()
    return job


def assert_same_as_team(world, online: dict, tol: float = 1e-8, config=None, backbone=None) -> int:
    team = Team(world.robot_ids, OverlapDescriptor(world), backbone or GTBackbone(world, seed=1), SensorDepthDouble(),
                config or CFG)
    ref = list(team.run_encounter(world.to_encounter()))
    n_direct = 0
    for t, res in enumerate(ref):
        for rid in world.robot_ids:
            mine = online[rid][t]
            want = [p for p in res.pairs if p.ego == rid]
            assert [(p.other, p.source, p.reason, p.gate_open, p.bytes_pair, p.anchor_step) for p in mine.pairs] \
                == [(p.other, p.source, p.reason, p.gate_open, p.bytes_pair, p.anchor_step) for p in want], (t, rid)
            for a, b in zip(mine.pairs, want):
                np.testing.assert_allclose(a.gate_score, b.gate_score, rtol=0, atol=0)
                assert (a.T_cj_ci is None) == (b.T_cj_ci is None)
                if a.T_cj_ci is not None:
                    np.testing.assert_allclose(a.T_cj_ci, b.T_cj_ci, atol=tol)
                n_direct += a.source == "direct"
            ro, rt = mine.robots[0], next(r for r in res.robots if r.robot == rid)
            assert dict(ro.bytes_sent) == dict(rt.bytes_sent), (t, rid)
            assert ro.degradations == rt.degradations, (t, rid)
            assert (ro.keyframe, ro.n_keyframes) == (rt.keyframe, rt.n_keyframes)
            np.testing.assert_allclose(ro.T_odom_cam, rt.T_odom_cam, atol=tol)
    return n_direct


@pytest.mark.parametrize("n_robots", [2, 3])
def test_lossless_nodes_equal_team(n_robots):
    world = make_world(n_robots, 12, seed=3, windows={(a, b): [(3, 6), (9, 11)] for a in range(n_robots)
                                                       for b in range(a + 1, n_robots)})
    nodes = make_nodes(world)
    out = run_threads({r: node_job(nodes[r], world, r) for r in world.robot_ids})
    n_direct = assert_same_as_team(world, out)
    assert n_direct == n_robots * (n_robots - 1) * 5  # the test exercises image exchange
    for r, node in nodes.items():
        assert node.stats["msg:lost"] == 0 and node.stats["replies_sent"] > 0, (r, dict(node.stats))
        assert node.stats["net:peer-lost"] == 0 and len(node.step_s) == world.n_steps


def test_shared_estimates_online_equal_team():
    """share_estimates over Zenoh: r0 cannot place r1's image, r1's estimate reaches it in the
    'estimate' frame of the same step; every record equals the in-process team's."""
    world = make_world(2, 12, seed=3, windows={(0, 1): [(3, 6), (9, 11)]})
    cfg = CFG.override({"messages.share_estimates": True})

    def blind(cur, key):
        return cur[0] == "r0" and len(key) == 3

    confs = link_confs(world.robot_ids)
    nodes = {r: make_node(world, r, confs[r], backbone=GTBackbone(world, seed=7, invalid=blind), config=cfg)
             for r in world.robot_ids}
    out = run_threads({r: node_job(nodes[r], world, r) for r in world.robot_ids})
    n_direct = assert_same_as_team(world, out, config=cfg, backbone=GTBackbone(world, seed=1, invalid=blind))
    assert n_direct == 2 * 5 - 2  # r0 holds r1's first two estimates until the third verifies them
    assert sum(p.direct_via == SHARED_VIA and p.source == "direct" for res in out["r0"] for p in res.pairs) == 3
    for r, node in nodes.items():
        assert node.stats["msg:lost"] == 0, (r, dict(node.stats))


def test_peer_comes_up_late_then_same_as_team():
    """r1 opens its session only after r0 has been dialing it for a while: Zenoh retries, both run in step."""
    world = make_world(2, 8, seed=4, windows={(0, 1): [(2, 5)]})
    p0, p1 = free_ports(2)
    node0 = make_node(world, "r0", {"team": "late", "multicast_scouting": False, "listen": [endpoint(p0)],
                                    "connect": [endpoint(p1)]})

    def late():
        time.sleep(1.5)
        node1 = make_node(world, "r1", {"team": "late", "multicast_scouting": False, "listen": [endpoint(p1)]})
        return node_job(node1, world, "r1")()

    out = run_threads({"r0": node_job(node0, world, "r0"), "r1": late})
    assert assert_same_as_team(world, out) > 0


def test_killed_peer_is_counted_and_robot_goes_on():
    world = make_world(2, 12, seed=5, windows={(0, 1): [(1, 4)]})
    nodes = make_nodes(world, conf={"step_timeout_s": 3.0})

    def crash():  # r1 runs 6 steps, then its process "dies": the session ends without a bye
        res = node_job(nodes["r1"], world, "r1", n_steps=6, close=False)()
        nodes["r1"].link.session.close()
        return res

    t0 = time.monotonic()
    out = run_threads({"r0": node_job(nodes["r0"], world, "r0"), "r1": crash})
    r0 = out["r0"]
    assert len(r0) == world.n_steps
    degr = [d for res in r0 for d in res.robots[0].degradations]
    assert degr.count("net:peer-lost") == 1
    # every later step misses r1's descriptor and pose: two lost frames each, without waiting for them
    for res in r0[8:]:
        assert res.robots[0].degradations.count("msg:lost") == 2
        (p,) = res.pairs
        assert p.source == "propagated" and "descriptor-missing" in p.reason and "stale-pose" in p.reason
    assert sum(nodes["r0"].step_s[8:]) < 3.0  # no deadline spent on a robot known gone
    assert time.monotonic() - t0 < 60


class SlowBackbone(GTBackbone):
    """A robot whose joint pass takes longer than its peers wait."""

    def __init__(self, *a, delay_s: float = 0.25, **k):
        super().__init__(*a, **k)
        self.delay_s = delay_s

    def infer(self, views):
        time.sleep(self.delay_s)
        return super().infer(views)


def test_slow_robot_neither_deadlocks_nor_stalls_its_peer():
    """r1's pass outlasts r0's step timeout: both finish every step, r0 counts what r1 delivered too late."""
    world = make_world(2, 8, seed=10)
    confs = link_confs(world.robot_ids)
    conf = {"step_timeout_s": 0.05}
    nodes = {"r0": make_node(world, "r0", confs["r0"], conf),
             "r1": make_node(world, "r1", confs["r1"], conf, backbone=SlowBackbone(world, seed=7))}
    out = run_threads({r: node_job(nodes[r], world, r) for r in world.robot_ids})
    assert [len(out[r]) for r in world.robot_ids] == [8, 8]
    assert nodes["r0"].stats["msg:lost"] > 0
    assert nodes["r0"].stats["msg:lost"] == sum(res.robots[0].degradations.count("msg:lost") for res in out["r0"])
    assert nodes["r0"].stats["net:peer-lost"] == 0 and nodes["r1"].stats["net:peer-lost"] == 0


def test_run_online_writes_a_run_folder_and_publishes_the_estimates(tmp_path: Path):
    """Two robots through run_online (GT plug-ins); a ROS 2 listener on r0's session decodes what they
    publish: one PoseWithCovarianceStamped per estimate, equal to the estimate in steps.csv."""
    world = make_world(2, 6, seed=8, windows={(0, 1): [(1, 4)]})
    setting = Setting("toy-online", [world.to_encounter("enc")])
    confs = link_confs(world.robot_ids, team="lab")
    (port,) = free_ports(1)
    for c in confs.values():  # the robots dial the listener: it hears them from their first sample on
        c["connect"].append(endpoint(port))
    got: list[tuple[str, bytes, bytes]] = []
    listener = zenoh.open(_raw_conf([], [endpoint(port)]))
    sub = listener.declare_subscriber("0/cerpe/lab/**", lambda s: got.append(
        (str(s.key_expr), s.payload.to_bytes(), s.attachment.to_bytes())))

    def job(rid):
        plugins = type("P", (), {"descriptor": OverlapDescriptor(world), "backbone": GTBackbone(world, seed=1),
                                 "depth": SensorDepthDouble()})
        node_conf = {**FAST, "ros": {"key_format": "rmw_zenoh", "distro": "jazzy"}}
        return lambda: run_online(tmp_path / "m.yaml", None, rid, tmp_path / rid, link_conf=confs[rid],
                                  node_conf=node_conf, setting=setting, plugins=plugins, config=CFG, progress=False)

    try:
        run_threads({r: job(r) for r in world.robot_ids})
        time.sleep(0.3)
    finally:
        sub.undeclare()
        listener.close()
    published = {}
    for key, cdr, att in got:
        seq, _, _ = ros.parse_rmw_attachment(att)
        msg = ros.decode_pose_cdr(cdr)
        published[(key, round(msg["stamp_s"], 6))] = msg
        C = msg["covariance"]  # the switch's covariance: its propagation model, in ROS order
        assert seq >= 1 and np.all(np.isfinite(C)) and np.allclose(C, C.T) and np.all(np.linalg.eigvalsh(C) > 0)
    for rid in world.robot_ids:
        other = "r1" if rid == "r0" else "r0"
        enc = tmp_path / rid / "enc"
        steps = pd.read_csv(enc / "steps.csv")
        assert set(steps["ego"]) == {rid} and len(steps) == world.n_steps
        assert (steps["source"] == "direct").sum() == 3 and steps["bytes_pair"].sum() > 0
        assert (enc / "DONE.json").is_file() and (enc / "odometry" / f"{rid}.tum").is_file()
        report = json.loads((enc / "online.json").read_text())
        assert report["n_steps"] == world.n_steps and report["link"].get("msg:lost", 0) == 0
        key = ros.zenoh_key(ros.topic_name("lab", rid, other), {**ros.default_conf})
        assert report["ros_keys"] == {other: key}
        est = steps[steps["source"] != "none"]
        assert report["estimates_published"] == len(est) > 0
        for _, row in est.iterrows():
            msg = published[(key, round(float(row["stamp_s"]), 6))]
            assert msg["frame_id"] == f"lab/{other}/camera_optical"
            t, qxyzw = se3_to_tq_xyzw(msg["T_cj_ci"])
            np.testing.assert_allclose(t, row[["est_tx", "est_ty", "est_tz"]].to_numpy(float), atol=1e-6)
            want = row[["est_qx", "est_qy", "est_qz", "est_qw"]].to_numpy(float)
            assert min(np.abs(qxyzw - want).max(), np.abs(qxyzw + want).max()) < 1e-6
    with pytest.raises(Exception, match="already finished"):
        job("r0")()


def _raw_conf(connect: list[str], listen: list[str]):
    c = zenoh.Config()
    for k, v in (("mode", "peer"), ("scouting/multicast/enabled", False), ("connect/endpoints", connect),
                 ("listen/endpoints", listen)):
        c.insert_json5(k, json.dumps(v))
    return c


def test_node_and_run_online_errors(tmp_path: Path):
    world = make_world(2, 3, seed=9)
    setting = Setting("toy", [world.to_encounter("enc"), world.to_encounter("enc2")])
    lconf = {"multicast_scouting": False, "listen": ["tcp/127.0.0.1:0"]}
    with pytest.raises(OnlineError, match=r"--robot 'r7'.*robots \['r0', 'r1'\]"):
        run_online(tmp_path / "m.yaml", "enc", "r7", tmp_path, link_conf=lconf, setting=setting)
    with pytest.raises(OnlineError, match="no encounter 'nope'"):
        run_online(tmp_path / "m.yaml", "nope", "r0", tmp_path, link_conf=lconf, setting=setting)
    with pytest.raises(OnlineError, match="has 2 encounters.*--encounter"):
        run_online(tmp_path / "m.yaml", None, "r0", tmp_path, link_conf=lconf, setting=setting)
    with pytest.raises(OnlineError, match="--method 'sift-ransac'"):
        run_online(tmp_path / "m.yaml", "enc", "r0", tmp_path, method="sift-ransac", setting=setting)
    for conf, err, match in [({"rate_hz": -1.0}, OnlineError, "rate_hz must be >= 0"),
                             ({"ros": {"key_format": "dds"}}, OnlineError, "--ros-keys 'dds'"),
                             ({"step_timout_s": 1.0}, ConfigError, "unknown option"),
                             ({"ros": {"key_format": "rmw_zenoh"}}, Exception, "--team 'my-lab'.*ROS name token")]:
        link = ZenohLink("r0", world.robot_ids, {**lconf, "team": "my-lab"})
        try:
            agent = RobotAgent("r0", 0, CFG, OverlapDescriptor(world), GTBackbone(world), SensorDepthDouble())
            with pytest.raises(err, match=match):
                RobotNode(agent, link, world.robot_ids, conf=conf)
        finally:
            link.close(0.0)


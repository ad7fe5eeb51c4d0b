"""cerpe.online: robot nodes in threads on localhost (ephemeral ports) against the in-process Team.

The key test: with no loss, every robot's per-step relative poses, gate scores,
sources, reasons and bytes equal what :class:`cerpe.algorithm.Team` produces for
the same encounter (GT test-double backbone, tests/gt_backbone.py). Each node has
its own backbone instance, which draws other random frames and units than the
Team's shared one: poses agree to floating-point precision, not bit for bit.
"""
from __future__ import annotations

import socket
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from cerpe.algorithm import CerpeConfig, RobotAgent, Team
from cerpe.messages import PoseMessage
from cerpe.online import net as netmod
from cerpe.online.cli import run_online
from cerpe.online.net import Address, NetTransport, OnlineError, parse_address, parse_peer
from cerpe.online.node import RobotNode
from cerpe.protocols import FrameContext
from cerpe.scene import Setting
from gt_backbone import GTBackbone, OverlapDescriptor, SensorDepthDouble, make_world

CFG = CerpeConfig(min_scale_pixels=20)
LOCAL = Address("127.0.0.1", 0)
FAST = {"step_timeout_s": 5.0, "connect_timeout_s": 10.0}


def frames(world, rid: str, n_steps: int | None = None):
    enc = world.to_encounter()
    r = enc.robots[enc.robot_ids.index(rid)]
    for t in range(enc.n_steps if n_steps is None else n_steps):
        yield r.image(t), FrameContext(rid, t, r.intrinsics, r.depth_m(t), 0), float(r.stamps_s[t])


def make_nodes(world, conf=None, robots=None):
    """One node per robot (own plug-in instances), transports bound on ephemeral ports, not yet connected."""
    robots = robots or world.robot_ids
    nets = {r: NetTransport(r, LOCAL) for r in robots}
    nodes = {}
    for r in robots:
        agent = RobotAgent(r, world.index(r), CFG, OverlapDescriptor(world), GTBackbone(world, seed=7),
                           SensorDepthDouble())
        nodes[r] = RobotNode(agent, world.robot_ids, [p for p in robots if p != r], nets[r], {**FAST, **(conf or {})})
    return nets, nodes


def connect(nets):
    for r, n in nets.items():
        n.connect({p: m.address for p, m in nets.items() if p != r})


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
        th.join(60)
    assert not any(th.is_alive() for th in ths), "a node hung"
    if errors:
        raise next(iter(errors.values()))
    return results


def node_job(node, net, world, rid, n_steps=None, close=True):
    def job():
        try:
            return list(node.run(frames(world, rid, n_steps)))
        finally:
            if close:
                net.close(linger_s=2.0)
    return job


def assert_same_as_team(world, online: dict, tol: float = 1e-8) -> int:
    team = Team(world.robot_ids, OverlapDescriptor(world), GTBackbone(world, seed=1), SensorDepthDouble(), CFG)
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
    world = make_world(n_robots, 16, seed=3, windows={(a, b): [(3, 6), (10, 12)] for a in range(n_robots)
                                                       for b in range(a + 1, n_robots)})
    nets, nodes = make_nodes(world)
    connect(nets)
    out = run_threads({r: node_job(nodes[r], nets[r], world, r) for r in world.robot_ids})
    n_direct = assert_same_as_team(world, out)
    assert n_direct == n_robots * (n_robots - 1) * 5  # the test exercises image exchange
    replies = sum(r.robots[0].bytes_sent.get("reply", 0) for rs in out.values() for r in rs)
    assert replies > 0
    for r in world.robot_ids:
        assert nodes[r].stats["msg:lost"] == 0 and nets[r].stats["peer_lost"] == 0


def test_peer_comes_up_late_then_same_as_team():
    """r1 binds its port only after r0 has dialed it for a while: r0 retries, both then run in step."""
    world = make_world(2, 8, seed=4, windows={(0, 1): [(2, 5)]})
    with socket.socket() as s:  # reserve a free port for the late robot, release it
        s.bind(("127.0.0.1", 0))
        port1 = s.getsockname()[1]
    net0 = NetTransport("r0", LOCAL)
    agent0 = RobotAgent("r0", 0, CFG, OverlapDescriptor(world), GTBackbone(world, seed=2), SensorDepthDouble())
    node0 = RobotNode(agent0, world.robot_ids, ["r1"], net0, FAST)
    net0.connect({"r1": Address("127.0.0.1", port1)})
    box = {}

    def late():
        time.sleep(1.0)
        net1 = NetTransport("r1", Address("127.0.0.1", port1))
        agent1 = RobotAgent("r1", 1, CFG, OverlapDescriptor(world), GTBackbone(world, seed=3), SensorDepthDouble())
        node1 = RobotNode(agent1, world.robot_ids, ["r0"], net1, FAST)
        net1.connect({"r0": net0.address})
        box["net1"] = net1
        return node_job(node1, net1, world, "r1")()

    out = run_threads({"r0": node_job(node0, net0, world, "r0"), "r1": late})
    assert net0.stats["dial_failures"] >= 1
    assert assert_same_as_team(world, out) > 0


def test_killed_peer_is_counted_and_robot_goes_on():
    world = make_world(2, 14, seed=5, windows={(0, 1): [(1, 4)]})
    nets, nodes = make_nodes(world, conf={"step_timeout_s": 3.0})
    connect(nets)

    def crash():  # r1 runs 6 steps, then its process "dies": sockets closed without a bye
        res = node_job(nodes["r1"], nets["r1"], world, "r1", n_steps=6, close=False)()
        nets["r1"].abort()
        return res

    out = run_threads({"r0": node_job(nodes["r0"], nets["r0"], world, "r0"), "r1": crash})
    r0 = out["r0"]
    assert len(r0) == world.n_steps
    degr = [d for res in r0 for d in res.robots[0].degradations]
    assert degr.count("net:peer-lost") == 1
    assert nets["r0"].stats["peer_lost"] == 1
    # every later step misses r1's descriptor and pose: two lost frames each, no waiting
    for res in r0[7:]:
        assert res.robots[0].degradations.count("msg:lost") == 2
        (p,) = res.pairs
        assert p.source == "propagated" and "descriptor-missing" in p.reason and "stale-pose" in p.reason


def test_garbled_frames_and_garbage_are_counted_not_raised():
    """A fake r1 speaks the protocol, then sends a frame with a bad checksum, then raw garbage."""
    world = make_world(2, 6, seed=6)
    net0 = NetTransport("r0", LOCAL)
    agent0 = RobotAgent("r0", 0, CFG, OverlapDescriptor(world), GTBackbone(world, seed=2), SensorDepthDouble())
    node0 = RobotNode(agent0, world.robot_ids, ["r1"], net0, {"step_timeout_s": 1.0, "connect_timeout_s": 10.0})
    fake = socket.socket()
    fake.bind(("127.0.0.1", 0))
    fake.listen(1)
    net0.connect({"r1": Address("127.0.0.1", fake.getsockname()[1])})  # r0 < r1: r0 dials the fake
    stranger = socket.create_connection(("127.0.0.1", net0.address.port))  # no hello at all
    stranger.sendall(b"GET / HTTP/1.0\r\n\r\n")

    def fake_r1():
        sock, _ = fake.accept()
        sock.settimeout(5)
        netmod.read_envelope(sock, threading.Event(), 4096)  # r0's hello
        sock.sendall(netmod.pack(netmod.T_HELLO, netmod.hello_payload("r1")))
        good = bytearray(PoseMessage(1, 0, np.eye(4)).encode())
        good[20] ^= 0xFF  # checksum no longer matches
        sock.sendall(netmod.pack(netmod.T_MSG, bytes(good)))
        sock.sendall(netmod.pack(netmod.T_MSG, b"xx"))  # too short to be a frame
        time.sleep(0.3)
        sock.sendall(b"\x00garbage that is no envelope" * 10)
        time.sleep(0.5)
        sock.close()

    out = run_threads({"r0": node_job(node0, net0, world, "r0"), "r1": fake_r1})
    stranger.close()
    fake.close()
    degr = [d for res in out["r0"] for d in res.robots[0].degradations]
    assert degr.count("msg:garbled") == 3
    assert net0.stats["garbled"] == 3 and net0.stats["bad_hello"] >= 1
    assert len(out["r0"]) == world.n_steps and all(p.source == "none" for res in out["r0"] for p in res.pairs)


def test_run_online_writes_a_run_folder(tmp_path: Path):
    world = make_world(2, 6, seed=8, windows={(0, 1): [(1, 4)]})
    setting = Setting("toy-online", [world.to_encounter("enc")])
    with socket.socket() as a, socket.socket() as b:
        a.bind(("127.0.0.1", 0))
        b.bind(("127.0.0.1", 0))
        ports = {"r0": a.getsockname()[1], "r1": b.getsockname()[1]}

    def job(rid):
        other = "r1" if rid == "r0" else "r0"
        plugins = type("P", (), {"descriptor": OverlapDescriptor(world), "backbone": GTBackbone(world, seed=1),
                                 "depth": SensorDepthDouble()})
        return lambda: run_online(tmp_path / "m.yaml", "enc", rid, Address("127.0.0.1", ports[rid]),
                                  {other: Address("127.0.0.1", ports[other])}, tmp_path / rid, setting=setting,
                                  plugins=plugins, config=CFG, node_conf=FAST, progress=False)

    run_threads({r: job(r) for r in ("r0", "r1")})
    for rid in ("r0", "r1"):
        enc = tmp_path / rid / "enc"
        steps = pd.read_csv(enc / "steps.csv")
        assert set(steps["ego"]) == {rid} and len(steps) == world.n_steps
        assert (steps["source"] == "direct").sum() == 3 and steps["bytes_pair"].sum() > 0
        assert (enc / "DONE.json").is_file() and (enc / "online.json").is_file()
        assert (enc / "odometry" / f"{rid}.tum").is_file()
    with pytest.raises(Exception, match="already finished"):
        job("r0")()


def test_addresses_and_cli_errors(tmp_path: Path):
    assert parse_address("10.0.0.2:7000") == Address("10.0.0.2", 7000)
    assert parse_address("[::1]:7001") == Address("::1", 7001)
    assert parse_peer("r1=host:7") == ("r1", Address("host", 7))
    for bad in ("10.0.0.2", "host:99999", ":7000", "host:port"):
        with pytest.raises(OnlineError, match="HOST:PORT"):
            parse_address(bad)
    with pytest.raises(OnlineError, match="ROBOT_ID=HOST:PORT"):
        parse_peer("10.0.0.2:7000")
    cmd = [sys.executable, "-m", "cerpe.cli", "online"]
    bad = subprocess.run(cmd + ["--robot", "r0", "--listen", "0.0.0.0", "--peer", "r1=127.0.0.1:1",
                                "--manifest", "x.yaml", "--encounter", "e"], capture_output=True, text=True)
    assert bad.returncode == 2 and "--listen '0.0.0.0'" in bad.stderr and "Traceback" not in bad.stderr
    world = make_world(2, 3, seed=9)
    setting = Setting("toy", [world.to_encounter("enc")])
    with pytest.raises(OnlineError, match=r"--robot 'r7'.*robots \['r0', 'r1'\]"):
        run_online(tmp_path / "m.yaml", "enc", "r7", LOCAL, {"r1": Address("127.0.0.1", 1)}, tmp_path,
                   setting=setting)
    with pytest.raises(OnlineError, match="no encounter 'nope'"):
        run_online(tmp_path / "m.yaml", "nope", "r0", LOCAL, {"r1": Address("127.0.0.1", 1)}, tmp_path,
                   setting=setting)
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        s.listen(1)
        with pytest.raises(OnlineError, match="cannot listen"):
            NetTransport("r0", Address("127.0.0.1", s.getsockname()[1]))


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
    nets, nodes = make_nodes(world, conf={"step_timeout_s": 0.05, "max_lag_steps": 1})
    nodes["r1"].agent.backbone = SlowBackbone(world, seed=7)
    connect(nets)
    out = run_threads({r: node_job(nodes[r], nets[r], world, r) for r in world.robot_ids})
    assert [len(out[r]) for r in world.robot_ids] == [8, 8]
    assert nodes["r0"].stats["msg:lost"] > 0
    assert nodes["r0"].stats["msg:lost"] == sum(res.robots[0].degradations.count("msg:lost") for res in out["r0"])
    assert nets["r0"].stats["peer_lost"] == 0 and nets["r1"].stats["peer_lost"] == 0

"""The step engine over ZenohLink equals the in-process Team (skipped until cerpe.algorithm.engine exists).

Robots run in threads of this process, one ZenohLink each on tcp/127.0.0.1 endpoints
(multicast off), with the GT test-double plug-ins of tests/gt_backbone.py. With no loss,
every robot's pair records, bytes and degradations equal Team's on the same encounter,
as tests/test_online.py checks for the TCP transport; a robot whose session dies is
counted (net:peer-lost) and the other finishes without waiting for it.
"""
from __future__ import annotations

import pytest

pytest.importorskip("zenoh")
engine = pytest.importorskip("cerpe.algorithm.engine", reason="needs the step engine (cerpe.algorithm package)")

from cerpe.algorithm import RobotAgent  # noqa: E402
from cerpe.online.zenoh_link import ZenohLink  # noqa: E402
from gt_backbone import GTBackbone, OverlapDescriptor, SensorDepthDouble, make_world  # noqa: E402
from test_online import CFG, assert_same_as_team, frames, run_threads  # noqa: E402
from test_online_zenoh_link import endpoint, free_ports  # noqa: E402

WAIT_S = 5.0


def make_links(world, team="eng"):
    ports = dict(zip(world.robot_ids, free_ports(len(world.robot_ids))))
    links = {}
    for k, r in enumerate(world.robot_ids):
        links[r] = ZenohLink(r, world.robot_ids, {
            "team": team, "multicast_scouting": False, "listen": [endpoint(ports[r])],
            "connect": [endpoint(ports[q]) for q in world.robot_ids[:k]]})
    return links


def robot_job(world, links, rid, n_steps=None, close=True):
    """One robot: its engine over its link, steps driven at once (the link's waits block)."""
    def job():
        link = links[rid]
        agent = RobotAgent(rid, world.index(rid), CFG, OverlapDescriptor(world), GTBackbone(world, seed=7),
                           SensorDepthDouble())
        eng = engine.StepEngine(agent, link, world.robot_ids, wait_s=WAIT_S)
        assert link.wait_peers(eng.peers, 10.0) == []
        try:
            return [engine.drive([eng.step(image, ctx, stamp)])[0] for image, ctx, stamp in frames(world, rid, n_steps)]
        finally:
            if close:
                link.close(linger_s=3.0)
    return job


@pytest.mark.parametrize("n_robots", [2, 3])
def test_lossless_engines_over_zenoh_equal_team(n_robots):
    world = make_world(n_robots, 12, seed=3, windows={(a, b): [(3, 6), (9, 11)] for a in range(n_robots)
                                                       for b in range(a + 1, n_robots)})
    links = make_links(world)
    out = run_threads({r: robot_job(world, links, r) for r in world.robot_ids})
    assert assert_same_as_team(world, out) > 0  # direct estimates: images went through the queryables
    for r, link in links.items():
        assert link.stats["msg:lost"] == 0 and link.stats["replies_sent"] > 0, (r, dict(link.stats))


def test_robot_whose_session_dies_is_counted_and_the_other_finishes():
    world = make_world(2, 10, seed=5, windows={(0, 1): [(1, 4)]})
    links = make_links(world)

    def crash():  # r1 runs 5 steps, then its session ends without a bye (what a killed process looks like)
        res = robot_job(world, links, "r1", n_steps=5, close=False)()
        links["r1"].session.close()
        return res

    out = run_threads({"r0": robot_job(world, links, "r0"), "r1": crash})
    r0 = out["r0"]
    assert len(r0) == world.n_steps
    degr = [d for res in r0 for d in res.robots[0].degradations]
    assert degr.count("net:peer-lost") == 1
    for res in r0[7:]:  # r1 known gone: its descriptor and pose are lost each step, without waiting
        assert res.robots[0].degradations.count("msg:lost") == 2

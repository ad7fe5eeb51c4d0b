"""Anchor verification, registrations through own views and the memory-aware gate, end to end with
the ground-truth doubles (tests/gt_backbone.py): injected wrong estimates, revisits through a keyframe."""
from __future__ import annotations

import dataclasses
from collections import Counter

import numpy as np
import pytest
from gt_backbone import (
    GTBackbone,
    OverlapDescriptor,
    SensorDepthDouble,
    World,
    make_follow_world,
    make_world,
)

from cerpe.algorithm import AlgorithmConfig, Team
from cerpe.geometry import (
    e_rot,
    make_se3,
    propagate_relative_pose,
    se3_inverse,
    so3_exp,
)

CFG = AlgorithmConfig().override({"scale.min_pixels": 20})


def run(world: World, config: AlgorithmConfig = CFG, descriptor=None, **backbone):
    bb = GTBackbone(world, seed=1, **backbone)
    team = Team(world.robot_ids, descriptor or OverlapDescriptor(world), bb, SensorDepthDouble(), config)
    return bb, list(team.run_encounter(world.to_encounter()))


def pair(results, ego: str, other: str) -> dict:
    return {res.step: next(p for p in res.pairs if p.ego == ego and p.other == other) for res in results}


def degradations(results, robot: str) -> Counter:
    return Counter(d for res in results for r in res.robots if r.robot == robot for d in r.degradations)


def gt_error(world: World, p) -> tuple[float, float]:
    gt = world.gt_T_cj_ci(p.step, world.index(p.ego), world.index(p.other))
    return float(e_rot(p.T_cj_ci, gt)), float(np.linalg.norm(p.T_cj_ci[:3, 3] - gt[:3, 3]))


def turned(angle: float) -> np.ndarray:
    return make_se3(so3_exp(np.array([0.0, angle, 0.0])), np.zeros(3))


def test_wrong_direct_estimate_is_rejected_and_counted_a_consistent_one_accepted():
    world = make_world(2, 40, seed=1)  # overlap windows 5-9 and 25-29
    wrong = {("r1", 27, "jpeg")}  # r0's pass at step 27 places r1's image 0.5 rad off
    _, results = run(world, perturb=lambda cur, via, key: turned(0.5) if key in wrong else None)
    P = pair(results, "r0", "r1")
    # two earlier estimates must agree with one (anchor_verify_support = 2)
    assert [P[t].anchor_verdict for t in range(5, 10)] == ["unverified"] * 2 + ["verified"] + ["accepted"] * 2
    assert P[5].source == P[6].source == "direct" and P[5].reason == P[6].reason == "unverified"
    assert P[7].reason == "" and P[7].check_rot_rad < 1e-6
    p = P[27]
    assert p.gate_open and p.anchor_verdict == "rejected" and p.check_rot_rad == pytest.approx(0.5, abs=1e-6)
    assert p.source == "propagated" and p.anchor_step == 26 and p.reason.startswith("direct-rejected")
    assert max(gt_error(world, p)) < 1e-5  # the anchor's propagation, not the wrong estimate
    assert P[28].source == "direct" and P[28].anchor_verdict == "accepted" and P[28].reason == ""
    assert degradations(results, "r0")["anchor:inconsistent"] == 1
    assert "anchor:inconsistent" in next(r for r in results[27].robots if r.robot == "r0").degradations
    assert degradations(results, "r1")["anchor:inconsistent"] == 0
    for res in results:
        for q in res.pairs:
            if q.source != "none":
                assert max(gt_error(world, q)) < 1e-5, (q.step, q.ego)


def test_a_weak_estimate_that_agrees_keeps_the_anchor_and_is_counted():
    world = make_world(2, 40, seed=1)  # overlap windows 5-9 and 25-29
    weak = ("r1", 27, "jpeg")  # r0's pass at step 27 places r1's image on 20 inliers, 0.05 rad off
    support = lambda cur, key: 20 if key == weak else 100  # noqa: E731
    nudge = lambda cur, via, key: turned(0.05) if key == weak else None  # noqa: E731
    _, results = run(world, support=support, perturb=nudge)
    p = pair(results, "r0", "r1")[27]
    assert p.gate_open and p.anchor_verdict == "weak" and p.check_rot_rad == pytest.approx(0.05, abs=1e-6)
    assert p.source == "propagated" and p.anchor_step == 26 and p.reason == "direct-weak" and p.direct_inliers == 20
    assert max(gt_error(world, p)) < 1e-5  # the anchor's propagation, not the weak estimate
    assert pair(results, "r0", "r1")[28].anchor_verdict == "accepted"
    assert degradations(results, "r0")["anchor:weak"] == 1 and degradations(results, "r0")["anchor:inconsistent"] == 0
    assert degradations(results, "r1")["anchor:weak"] == 0
    # without propagation (w/o EM) the weak step reports nothing; with the rule off it is reported
    _, results = run(world, CFG.override({"backend.propagate": False}), support=support, perturb=nudge)
    assert pair(results, "r0", "r1")[27].source == "none"
    _, results = run(world, CFG.override({"anchors.min_inliers": 0}), support=support, perturb=nudge)
    p = pair(results, "r0", "r1")[27]
    assert p.source == "direct" and p.anchor_verdict == "accepted" and gt_error(world, p)[0] > 0.04


def _world_turn(world: World, key, angle: float, about: np.ndarray) -> np.ndarray:
    """Right-hand perturbation that places view ``key`` in a world turned by ``angle`` about the point
    ``about``: every such placement is wrong by the same rigid motion, so they agree with each other."""
    G = make_se3(np.eye(3), about) @ turned(angle) @ make_se3(np.eye(3), -about)
    W = world.pose(key)
    return se3_inverse(W) @ G @ W


@pytest.mark.parametrize("n", [2, 3])
def test_persistent_disagreement_replaces_a_wrong_anchor(n):
    world = make_world(2, 40, seed=1)
    centre = world.T_world_cam[0, 7, :3, 3]
    _, results = run(world, CFG.override({"anchors.replace_after": n}),
                     perturb=lambda cur, via, key: _world_turn(world, key, 0.6, centre)
                     if len(key) == 3 and 5 <= key[1] < 10 else None)
    for ego, other in (("r0", "r1"), ("r1", "r0")):
        P = pair(results, ego, other)
        assert P[7].anchor_verdict == "verified"  # wrong, but the first window agrees with itself
        assert gt_error(world, P[9])[0] > 0.5
        assert [P[t].anchor_verdict for t in range(25, 30)] == ["rejected"] * (n - 1) + ["replaced"] + \
            ["accepted"] * (5 - n)
        for t in range(25, 24 + n):
            assert P[t].source == "propagated" and P[t].anchor_step == 9
        t = 24 + n
        assert P[t].source == "direct" and P[t].reason == "" and max(gt_error(world, P[t])) < 1e-5
        for t in range(30, 40):
            assert P[t].anchor_step == 29 and max(gt_error(world, P[t])) < 1e-5
        d = degradations(results, ego)
        assert (d["anchor:inconsistent"], d["anchor:replaced"]) == (n - 1, 1)


def test_unverified_estimate_is_not_carried_beyond_max_unverified_steps():
    world = make_world(2, 16, seed=2, windows={(0, 1): [(5, 6)]})
    for limit in (3, 1):
        _, results = run(world, CFG.override({"anchors.max_unverified_steps": limit}))
        for ego, other in (("r0", "r1"), ("r1", "r0")):
            P = pair(results, ego, other)
            assert (P[5].source, P[5].reason, P[5].anchor_verdict) == ("direct", "unverified", "unverified")
            for t in range(6, 6 + limit):
                assert (P[t].source, P[t].reason, P[t].anchor_step) == ("propagated", "unverified", 5)
                assert max(gt_error(world, P[t])) < 1e-5
            for t in range(6 + limit, 16):
                assert (P[t].source, P[t].reason) == ("none", "unverified-expired")
            assert all(P[t].reason == "no-anchor" for t in range(5))


def test_unverified_estimates_are_held_without_report_unverified():
    """``report_unverified=False``: an estimate nothing agrees with yet is not reported nor carried;
    the first verified one is, and from then on the pair is as with reporting (a wrong estimate
    injected after the anchor is still rejected and counted)."""
    world = make_world(2, 40, seed=1)  # overlap windows 5-9 and 25-29
    wrong = {("r1", 27, "jpeg")}
    config = CFG.override({"anchors.report_unverified": False})
    _, results = run(world, config, perturb=lambda cur, via, key: turned(0.5) if key in wrong else None)
    P = pair(results, "r0", "r1")
    assert [P[t].anchor_verdict for t in range(5, 10)] == ["unverified"] * 2 + ["verified"] + ["accepted"] * 2
    for t in (5, 6):
        assert (P[t].source, P[t].reason, P[t].anchor_step) == ("none", "unverified-held", -1)
        assert P[t].T_cj_ci is None and P[t].T_direct is not None  # judged, recorded, not reported
    assert P[7].source == "direct" and P[7].reason == "" and max(gt_error(world, P[7])) < 1e-5
    assert P[27].anchor_verdict == "rejected" and P[27].source == "propagated"
    assert degradations(results, "r0")["anchor:inconsistent"] == 1
    # a lone estimate (one step of overlap) is never reported: nothing agrees with it
    world = make_world(2, 16, seed=2, windows={(0, 1): [(5, 6)]})
    _, results = run(world, config)
    P = pair(results, "r0", "r1")
    assert (P[5].source, P[5].reason, P[5].anchor_verdict) == ("none", "unverified-held", "unverified")
    assert all((P[t].source, P[t].reason) == ("none", "unverified-held") for t in range(6, 16))
    assert all(P[t].reason == "no-anchor" for t in range(5))


def test_an_odometry_jump_drops_the_anchor_instead_of_carrying_it_wrong():
    """r1's pass places its own frame of step 15 turned by 1.5 rad (a lost track): its odometry jumps.
    Both pairs forget their (right) anchors there and count it, report nothing until the next window
    verifies a new one; with the check off the anchor is carried 1.5 rad wrong until replaced."""
    world = make_world(2, 40, seed=1)  # overlap windows 5-9 and 25-29
    jump = lambda cur, via, key: turned(1.5) if key == ("r1", 15) and cur == key else None
    _, results = run(world, perturb=jump)  # anchor_max_odo_rot_step = 1.0 (the default)
    for ego, other in (("r0", "r1"), ("r1", "r0")):
        P = pair(results, ego, other)
        assert P[14].source == "propagated" and max(gt_error(world, P[14])) < 1e-5
        assert all((P[t].source, P[t].reason) == ("none", "no-anchor") for t in range(15, 25))
        assert [P[t].anchor_verdict for t in range(25, 30)] == ["unverified"] * 2 + ["verified"] + ["accepted"] * 2
        assert all(max(gt_error(world, P[t])) < 1e-5 for t in range(25, 40))
        assert degradations(results, ego)["anchor:odometry-jump"] == 1
    _, results = run(world, CFG.override({"anchors.max_odo_rot_step": 0.0}), perturb=jump)
    P = pair(results, "r0", "r1")
    assert all(P[t].source == "propagated" and gt_error(world, P[t])[0] > 1.4 for t in range(15, 29))
    assert P[29].anchor_verdict == "replaced" and degradations(results, "r0")["anchor:odometry-jump"] == 0


def test_two_registrations_that_agree_verify_at_once():
    world = make_world(2, 14, seed=3)
    register = lambda own, col: 100 if own[1] == col[1] else 40
    _, results = run(world, register=register)
    P = pair(results, "r0", "r1")
    assert P[5].anchor_verdict == "verified" and P[5].reason == "" and P[5].direct_via == -1
    assert P[5].check_rot_rad < 1e-6 and max(gt_error(world, P[5])) < 1e-5
    # the same with the registrations through older views wrong by 0.3 rad: no second estimate
    _, results = run(world, register=register,
                     perturb=lambda cur, via, key: turned(0.3) if via is not None and via[1] != key[1] else None)
    P = pair(results, "r0", "r1")
    assert P[5].anchor_verdict == "unverified" and P[5].direct_via == -1
    assert max(gt_error(world, P[5])) < 1e-5  # the most inliers: through the current view
    assert P[6].anchor_verdict == "unverified" and P[7].anchor_verdict == "verified"  # steps 5, 6 propagated


def test_a_joint_pass_estimate_carries_the_support_that_placed_the_collaborator():
    """Without registrations the direct estimate comes through the joint pass; its inliers are the
    backbone's ``support`` of the collaborator view (-1 where the backbone gives none)."""
    world = make_world(2, 14, seed=3)
    _, results = run(world, support=lambda cur, key: 60 + cur[1] if len(key) == 3 else 500)
    P = pair(results, "r0", "r1")
    direct = [t for t in P if P[t].source == "direct"]
    assert direct and all(P[t].direct_via == -1 and P[t].direct_inliers == 60 + t for t in direct)
    _, results = run(world)
    P = pair(results, "r0", "r1")
    assert all(P[t].direct_inliers == -1 for t in P if P[t].source == "direct")


def test_registration_through_an_older_own_view_is_composed_through_the_pass_or_the_odometry():
    """Only older own views register the collaborator: the estimate goes through them; through the
    joint pass when it placed them with the current view, else through the robot's own odometry."""
    world = make_world(2, 14, seed=4)
    register = lambda own, col: 100 - (col[1] - own[1]) if own[1] < col[1] - 1 else 0
    for unplaced in (False, True):  # True: the pass places neither the collaborator nor the registering views
        invalid = (lambda cur, key: len(key) == 3 or (key[0] == cur[0] and key[1] < cur[1] - 1)) if unplaced else None
        # a constant unit: the scale of a pass whose older keyframes are not placed falls back to the last one
        _, results = run(world, register=register, invalid=invalid, unit_range=(2.0, 2.0))
        P = pair(results, "r0", "r1")
        for t in range(5, 10):
            assert P[t].source == "direct" and 0 <= P[t].direct_via < t - 1
            assert max(gt_error(world, P[t])) < 1e-5


def test_robots_anchor_through_a_keyframe_when_one_sees_later_what_the_other_saw():
    """r1 sees at steps 20-22 what r0 saw at steps 5-7, never what r0 sees at the same time: r0's
    memory-aware gate opens on its keyframe, r1's image registers against that keyframe (which the
    joint pass no longer places), and the estimate is composed through r0's odometry."""
    world = make_follow_world(n_steps=30, delay=15, seed=5)
    places = {(r, s + d): f"place-{s}" for s in (5, 6, 7) for r, d in (("r0", 0), ("r1", 15))}
    desc = OverlapDescriptor(world, places=places)
    config = CFG.override({"memory.tau_m": 0.99, "memory.tau_k": 0.2, "memory.delta_k": 0, "memory.capacity": 20})  # keep every frame
    register = lambda own, col: 80 if places.get(own) is not None and places.get(own) == places.get(col[:2]) \
        else 0
    old = lambda cur, key: cur[0] == "r0" and cur[1] >= 20 and (len(key) == 3 or key[1] < 10)
    bb, results = run(world, config, desc, register=register, invalid=old)
    P = pair(results, "r0", "r1")
    for t in range(30):
        assert P[t].gate_score < config.resolved().gate.tau  # never at the same time
    for t, kf in ((20, 5), (21, 6), (22, 7)):
        assert ("r0", kf) in bb.calls[2 * t]  # the keyframe is in r0's pass
        p = P[t]
        assert p.gate_open and p.gate_via == kf and p.gate_score_memory == pytest.approx(0.65, abs=1e-3)
        assert p.source == "direct" and p.direct_via == kf
        assert max(gt_error(world, p)) < 1e-5
    assert [P[t].anchor_verdict for t in (20, 21, 22)] == ["unverified", "unverified", "verified"]
    for t in range(23, 30):
        assert P[t].source == "propagated" and P[t].anchor_step == 22 and max(gt_error(world, P[t])) < 1e-5
    assert all(P[t].source == "none" for t in range(20))
    Q = pair(results, "r1", "r0")  # r1 never saw what r0 sees
    assert all(not Q[t].gate_open and Q[t].source == "none" for t in range(30))
    # the paper's gate (current frame only) never opens here
    _, results = run(world, config.override({"gate.memory_aware": False}), desc, register=register, invalid=old)
    assert all(p.source == "none" and not p.gate_open for res in results for p in res.pairs)


def test_verify_anchors_false_is_the_papers_switching():
    """Every direct estimate becomes the anchor, wrong or not; every other step propagates the last one."""
    world = make_world(2, 40, seed=1)
    wrong = {("r1", 27, "jpeg"), ("r0", 7, "jpeg")}
    config = CFG.override({"anchors.verify": False, "gate.memory_aware": False})
    _, results = run(world, config, rot_noise_rad=0.01, trans_noise=0.05,
                     perturb=lambda cur, via, key: turned(0.5) if key in wrong else None)
    X = {(r.robot, res.step): r.T_odom_cam for res in results for r in res.robots}
    for ego, other in (("r0", "r1"), ("r1", "r0")):
        last = None
        for t, p in sorted(pair(results, ego, other).items()):
            if 5 <= t < 10 or 25 <= t < 30:
                assert p.source == "direct" and p.anchor_verdict == "unchecked" and p.reason == ""
                last = (t, p.T_cj_ci)
            elif last is None:
                assert p.source == "none" and p.reason == "no-anchor"
            else:
                a, T = last
                want = propagate_relative_pose(T, X[(ego, a)], X[(ego, t)], X[(other, a)], X[(other, t)])
                assert p.source == "propagated" and p.anchor_step == a
                np.testing.assert_allclose(p.T_cj_ci, want, atol=1e-12)
    P = pair(results, "r0", "r1")
    assert gt_error(world, P[27])[0] > 0.45 and gt_error(world, P[28])[0] < 0.1
    assert not any(d.startswith("anchor:") for res in results for r in res.robots for d in r.degradations)


def test_a_translation_outlier_among_the_first_estimates_is_dropped_and_counted():
    """r0's pass at step 6 places r1's image 15 m off in the world with the right rotation: it joins no
    group (5, 7, 8 agree), the group verifies at step 8 (anchor_verify_support 2) and step 6 is
    counted as rejected (``anchor:inconsistent``) then; everything reported after is right."""
    world = make_world(2, 40, seed=1)  # overlap windows 5-9 and 25-29
    G = make_se3(np.eye(3), np.array([15.0, 0.0, 0.0]))
    W = world.pose(("r1", 6, "jpeg"))
    _, results = run(world, perturb=lambda cur, via, key: se3_inverse(W) @ G @ W if key == ("r1", 6, "jpeg") else None)
    P = pair(results, "r0", "r1")
    assert [P[t].anchor_verdict for t in range(5, 10)] == ["unverified"] * 3 + ["verified", "accepted"]
    assert gt_error(world, P[6])[0] < 1e-5 and gt_error(world, P[6])[1] > 5.0  # reported unverified
    assert P[8].reason == "" and max(gt_error(world, P[8])) < 1e-5
    assert degradations(results, "r0")["anchor:inconsistent"] == 1
    assert "anchor:inconsistent" in next(r for r in results[8].robots if r.robot == "r0").degradations
    assert degradations(results, "r1")["anchor:inconsistent"] == 0
    for t in range(8, 40):
        if P[t].source != "none":
            assert max(gt_error(world, P[t])) < 1e-5, t

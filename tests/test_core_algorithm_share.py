"""Shared direct estimates (``AlgorithmConfig.share_estimates``, our extension): the wire frame and a team
in which only one robot can place the other's image (tests/gt_backbone.py)."""
from __future__ import annotations

from collections import Counter

import numpy as np
import pytest

from cerpe.algorithm import AlgorithmConfig, Team
from cerpe.algorithm.direct import SHARED_VIA
from cerpe.geometry import e_pos, e_rot, make_se3, random_se3, so3_exp
from cerpe.messages import EstimateMessage, MessageError, decode
from cerpe.transport import Channel
from gt_backbone import GTBackbone, OverlapDescriptor, SensorDepthDouble, make_world


def test_estimate_frame_round_trip_and_bad_frames():
    rng = np.random.default_rng(0)
    T1, T2 = random_se3(rng), random_se3(rng)
    msg = EstimateMessage(3, 17, ((0, T1, 120), (5, T2, -1)))
    frame = msg.encode()
    assert len(frame) == 14 + 2 + 2 * 62
    got = decode(frame)
    assert isinstance(got, EstimateMessage) and (got.sender, got.step) == (3, 17)
    np.testing.assert_allclose(got.for_target(0)[0], T1, atol=1e-12)
    assert got.for_target(0)[1] == 120 and got.for_target(5)[1] == -1 and got.for_target(1) is None
    empty = decode(EstimateMessage(1, 2).encode())
    assert empty.estimates == () and empty.for_target(0) is None
    bad = bytearray(frame)
    bad[20] ^= 0xFF
    with pytest.raises(MessageError, match="checksum"):
        decode(bytes(bad))
    with pytest.raises(MessageError):
        EstimateMessage(0, 0, ((1, np.full((4, 4), np.nan), 3),)).encode()
    with pytest.raises(MessageError, match="out of range"):
        EstimateMessage(0, 0, ((1, T1, -5),)).encode()


def _team(world, share: bool, channel: Channel | None = None, perturb=None, register=None,
          policy: dict | None = None) -> Team:
    # r0's passes never place r1's image (r0 has no view of where r1 is); r1's place r0's
    bb = GTBackbone(world, seed=1, invalid=lambda cur, key: cur[0] == "r0" and len(key) == 3, perturb=perturb,
                    register=register)
    return Team(world.robot_ids, OverlapDescriptor(world), bb, SensorDepthDouble(),
                AlgorithmConfig().override({"scale.min_pixels": 20, "messages.share_estimates": share, "policy": policy or {}}), channel)


def _records(world, share: bool, channel: Channel | None = None, perturb=None, register=None,
             policy: dict | None = None):
    team = _team(world, share, channel, perturb, register, policy)
    return list(team.run_encounter(world.to_encounter()))


def test_a_robot_that_cannot_place_its_peer_takes_the_peer_estimate():
    world = make_world(2, 30, seed=4)
    off, on = _records(world, False), _records(world, True)
    direct_steps = [t for t in range(30) if 5 <= t < 10 or 25 <= t < 30]
    for res_off, res_on in zip(off, on):
        t = res_on.step
        p_off = {p.ego: p for p in res_off.pairs}
        p_on = {p.ego: p for p in res_on.pairs}
        # r1 places r0's image itself: its estimates are the same with and without sharing
        assert p_on["r1"].source == p_off["r1"].source
        if p_on["r1"].T_cj_ci is not None:
            np.testing.assert_allclose(p_on["r1"].T_cj_ci, p_off["r1"].T_cj_ci, atol=1e-9)
        if t in (5, 6):  # r1's first two estimates: held until a third verifies them (r0 cannot check them)
            q = p_on["r0"]
            assert (q.source, q.direct_via, q.reason) == ("none", SHARED_VIA, "unverified-held")
            assert p_on["r1"].source == "direct" and "unverified" in p_on["r1"].reason  # r1 reports its own
        elif t in direct_steps:
            assert p_off["r0"].source != "direct"  # without sharing r0 never has a direct estimate
            q = p_on["r0"]
            assert q.source == "direct" and q.direct_via == SHARED_VIA and "shared-estimate" in q.reason
            gt = world.gt_T_cj_ci(t, 0, 1)
            assert e_pos(q.T_cj_ci[:3, 3], gt[:3, 3]) < 1e-5 and e_rot(q.T_cj_ci, gt) < 1e-6
        elif t > 5:  # between the windows r0 propagates the shared anchor, as its own
            assert p_on["r0"].source == "propagated" and p_off["r0"].source == "none"
    sent_on = Counter(k for res in on for r in res.robots for k, n in r.bytes_sent.items() if n)
    sent_off = Counter(k for res in off for r in res.robots for k, n in r.bytes_sent.items() if n)
    assert sent_on["estimate"] == 2 * 30 and "estimate" not in sent_off  # off: not a byte more


def test_lost_and_garbled_estimate_frames_are_counted_not_raised():
    world = make_world(2, 30, seed=4)
    results = _records(world, True, Channel(p_drop=0.3, p_garble=0.2, seed=3))
    degr = Counter(d for res in results for r in res.robots for d in r.degradations)
    assert any(k.startswith("msg:") for k in degr)
    for res in results:
        for p in res.pairs:
            if p.T_cj_ci is not None:
                assert np.all(np.isfinite(p.T_cj_ci))


def test_a_wrong_shared_estimate_is_judged_as_an_own_one():
    """r1's pass at step 27 places r0's image 0.5 rad off: r1 rejects it against its anchor, and so
    does r0, which gets it shared (inverted): both report the anchor's propagation and count it."""
    world = make_world(2, 30, seed=4)
    turn = make_se3(so3_exp(np.array([0.0, 0.5, 0.0])), np.zeros(3))
    results = _records(world, True, perturb=lambda cur, via, key: turn if key == ("r0", 27, "jpeg") else None)
    for ego in ("r0", "r1"):
        p = next(q for q in results[27].pairs if q.ego == ego)
        assert p.anchor_verdict == "rejected" and p.check_rot_rad == pytest.approx(0.5, abs=1e-6)
        assert p.source == "propagated" and p.reason.startswith("direct-rejected")
        gt = world.gt_T_cj_ci(27, world.index(ego), world.index(p.other))
        assert e_rot(p.T_cj_ci, gt) < 1e-6
        assert "anchor:inconsistent" in next(r for r in results[27].robots if r.robot == ego).degradations
    assert next(q for q in results[27].pairs if q.ego == "r0").direct_via == SHARED_VIA


@pytest.mark.parametrize("inliers, used", [(60, True), (39, False)])
def test_a_shared_estimate_below_the_anchor_bar_is_not_used(inliers, used):
    """r1 registers r0's image (against its current view) on ``inliers`` keypoints: at 40
    (anchor_min_inliers) and above r0 takes it, below r0 has no direct estimate at all."""
    world = make_world(2, 30, seed=4)

    def register(own, collab):
        return inliers if own[0] == "r1" and own[1] == collab[1] else 0

    results = _records(world, True, register=register)
    for t in range(7, 10):  # 5 and 6: held until verified (test above)
        q = next(p for p in results[t].pairs if p.ego == "r0")
        assert (q.source == "direct" and q.direct_via == SHARED_VIA and q.direct_inliers == inliers) == used, t
        r1 = next(p for p in results[t].pairs if p.ego == "r1")
        assert r1.direct_inliers == inliers  # r1 placed it (its own rules judge it: weak below 40)


def test_shared_estimates_do_not_replace_an_anchor_of_the_robot_own():
    """r0 places r1's image itself in the first window (its own anchor) but not in the second: there
    r1's estimates are not used, r0 propagates its own anchor; without any own anchor (the tests
    above) shared estimates replace the anchors shared estimates made, as own ones replace own ones."""
    world = make_world(2, 30, seed=4)
    bb = GTBackbone(world, seed=1, invalid=lambda cur, key: cur[0] == "r0" and len(key) == 3 and key[1] >= 20)
    team = Team(world.robot_ids, OverlapDescriptor(world), bb, SensorDepthDouble(),
                AlgorithmConfig().override({"scale.min_pixels": 20, "messages.share_estimates": True}))
    P = {res.step: next(q for q in res.pairs if q.ego == "r0") for res in team.run_encounter(world.to_encounter())}
    assert all(P[t].source == "direct" and P[t].direct_via != SHARED_VIA for t in range(5, 10))
    for t in range(25, 30):
        assert P[t].source == "propagated" and P[t].anchor_step == 9, t
        gt = world.gt_T_cj_ci(t, 0, 1)
        assert e_pos(P[t].T_cj_ci[:3, 3], gt[:3, 3]) < 1e-5 and e_rot(P[t].T_cj_ci, gt) < 1e-6


def test_a_robot_that_cannot_place_its_peer_skips_requests_while_the_peer_shares(monkeypatch):
    """policy.SHARED_SKIP_MISSES 2 (shipped), SHARED_RETRY_STEPS 4: r0 asks at 5 and 6 (both place nothing),
    skips 7-9 while r1 shares, asks at 25 (r1 shared nothing since 9), skips 26-28 and asks again at 29.
    r0's estimates are those of sharing without the rule (its own images never placed); r1 sends fewer replies."""
    from cerpe.algorithm import policy as policy_mod

    world = make_world(2, 30, seed=4)
    monkeypatch.setattr(policy_mod, "SHARED_RETRY_STEPS", 4)
    on = _records(world, True)
    monkeypatch.setattr(policy_mod, "SHARED_SKIP_MISSES", 1 << 30)  # the rule never acts
    plain = _records(world, True)
    skipped = [res.step for res in on for p in res.pairs if p.ego == "r0" and p.request_skipped]
    assert skipped == [7, 8, 9, 26, 27, 28]
    for res, ref in zip(on, plain):
        q, q_ref = (next(p for p in r.pairs if p.ego == "r0") for r in (res, ref))
        assert (q.source, q.direct_via) == (q_ref.source, q_ref.direct_via), res.step
        if q.T_cj_ci is not None:
            np.testing.assert_allclose(q.T_cj_ci, q_ref.T_cj_ci, atol=1e-9)
        if q.request_skipped:
            assert q.reason == "request-skipped: peer-shares" or q.direct_via == SHARED_VIA
        r1, r1_ref = (next(p for p in r.pairs if p.ego == "r1") for r in (res, ref))
        assert r1.source == r1_ref.source  # r1 asks as before: its images place
    replies = [sum(r.bytes_sent.get("reply", 0) for res in run for r in res.robots if r.robot == "r1")
               for run in (on, plain)]
    assert 0 < replies[0] < replies[1]


def test_a_shared_estimate_on_more_inliers_than_the_robot_own_is_the_one_offered():
    """r0 places r1's image on 15 inliers, 0.05 rad off; r1 places r0's on 200, exactly. The two agree
    within the anchor tolerance and verify each other; r0 reports and anchors r1's (the stronger),
    so its propagation between the windows is exact (before, r0 anchored its own, 0.05 rad off)."""
    world = make_world(2, 30, seed=4)
    turn = make_se3(so3_exp(np.array([0.0, 0.05, 0.0])), np.zeros(3))

    def register(own, collab):
        return {"r0": 15, "r1": 200}[own[0]] if own[1] == collab[1] else 0

    results = _records(world, True, perturb=lambda cur, via, key: turn if key[0] == "r1" and len(key) == 3 else None,
                       register=register)
    P = {res.step: next(p for p in res.pairs if p.ego == "r0") for res in results}
    assert P[5].source == "direct" and P[5].direct_via == SHARED_VIA and P[5].direct_inliers == 200
    assert P[5].anchor_verdict == "verified"
    for t in range(10, 25):
        assert P[t].source == "propagated" and e_rot(P[t].T_cj_ci, world.gt_T_cj_ci(t, 0, 1)) < 1e-6, t

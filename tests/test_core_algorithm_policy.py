"""The image-request policy: the rules on their own, then end to end with the ground-truth doubles
(tests/gt_backbone.py), where anchors verify and the policy can skip."""
from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from gt_backbone import GTBackbone, OverlapDescriptor, SensorDepthDouble, make_world

from cerpe.algorithm import AlgorithmConfig, Team
from cerpe.algorithm import policy as policy_mod
from cerpe.algorithm.policy import (
    AskLog,
    PairView,
    PolicyConfig,
    PolicyError,
    after_request,
    backoff_steps,
    decide,
    propagation_sigma,
    skip_for_shared,
    try_hard,
)
from cerpe.geometry import e_rot

PAYS = PolicyConfig(mode="pays")
FRESH = PairView(anchored=True, steps_since=1, travelled_m=0.5)


def test_pays_skips_a_fresh_certain_anchor_and_asks_otherwise():
    assert decide(PAYS, True, FRESH) == (False, "anchor-fresh")
    assert decide(PAYS, True, PairView(anchored=False)) == (True, "no-anchor")
    assert decide(PAYS, True, None) == (True, "no-anchor")
    # an unverified candidate (no anchor yet) or challengers of the anchor wait for more estimates
    assert decide(PAYS, True, PairView(anchored=False, pending=True))[0]
    assert decide(PAYS, True, dataclasses.replace(FRESH, pending=True)) == (True, "pending")
    assert decide(PAYS, True, dataclasses.replace(FRESH, steps_since=31)) == (True, "stale")
    # the graph's sigma, when there is one, decides instead of the propagation model
    assert decide(PAYS, True, dataclasses.replace(FRESH, sigma_rot_rad=0.06, sigma_pos_m=0.1)) == (True, "uncertain")
    assert decide(PAYS, True, dataclasses.replace(FRESH, sigma_rot_rad=0.01, sigma_pos_m=0.31)) == (True, "uncertain")
    assert decide(PAYS, True, dataclasses.replace(FRESH, steps_since=20, sigma_rot_rad=0.01,
                                                  sigma_pos_m=0.1)) == (False, "anchor-fresh")
    # the propagation model: rotation grows per step, position per metre travelled
    assert decide(PAYS, True, dataclasses.replace(FRESH, steps_since=12)) == (True, "uncertain")  # 0.01+0.042
    assert decide(PAYS, True, dataclasses.replace(FRESH, travelled_m=5.1)) == (True, "uncertain")  # 0.05+0.255
    assert propagation_sigma(PairView(True, steps_since=10, travelled_m=2.0)) == pytest.approx((0.045, 0.15))
    # never without the gate, except "always"
    assert decide(PAYS, False, PairView(anchored=False)) == (False, "gate-closed")
    assert decide(PolicyConfig(), False, None) == (False, "gate-closed")
    assert decide(PolicyConfig(), True, FRESH) == (True, "gate")  # the paper's: whenever the gate opens
    assert decide(PolicyConfig(mode="always"), False, FRESH) == (True, "always")


@pytest.mark.parametrize("bad", [{"mode": "sometimes"}, {"max_steps": -1}, {"max_steps": 1.5},
                                 {"max_sigma_rot_rad": float("nan")}, {"max_sigma_pos_m": -0.1},
                                 {"miss_limit": -1}, {"miss_backoff_steps": True}, {"recheck_rot_rad": -0.1},
                                 {"recheck_limit": -1}, {"backoff_pending_exempt": 1},
                                 {"unanchored_backoff_steps": -2}])
def test_bad_policy_config_is_one_clear_error(bad):
    with pytest.raises(PolicyError, match=next(iter(bad))):
        PolicyConfig(**bad)
    with pytest.raises(PolicyError, match="policy." + next(iter(bad))):
        AlgorithmConfig().override({"policy": bad})
    with pytest.raises(PolicyError, match="unknown key 'policy.modus'; known under policy: mode, "):
        AlgorithmConfig().override({"policy.modus": "pays"})


def _run(policy: dict, backend: str = "switch"):
    world = make_world(2, 40, seed=1)  # overlap windows 5-9 and 25-29
    cfg = AlgorithmConfig().override({"scale.min_pixels": 20, "policy": policy, "backend.kind": backend})
    team = Team(world.robot_ids, OverlapDescriptor(world), GTBackbone(world, seed=1), SensorDepthDouble(), cfg)
    results = list(team.run_encounter(world.to_encounter()))
    P = {res.step: next(p for p in res.pairs if p.ego == "r0" and p.other == "r1") for res in results}
    return world, results, P


def test_agent_skips_requests_while_the_anchor_is_fresh_and_asks_again_when_it_is_not():
    world, results, P = _run({"mode": "pays"})
    _, base, B = _run({"mode": "gate"})
    # verification still works: the unverified candidates keep asking until one is verified
    assert [P[t].anchor_verdict for t in range(5, 8)] == ["unverified", "unverified", "verified"]
    assert [B[t].anchor_verdict for t in range(5, 8)] == ["unverified", "unverified", "verified"]
    assert all(P[t].bytes_pair > 0 and not P[t].request_skipped for t in range(5, 8))
    # a fresh verified anchor with a low predicted sigma: the open gate asks for nothing
    for t in (8, 9):
        p = P[t]
        assert p.gate_open and p.request_skipped and p.bytes_pair == 0 and p.anchor_verdict == ""
        assert p.source == "propagated" and p.anchor_step == 7 and p.reason == "request-skipped: anchor-fresh"
        gt = world.gt_T_cj_ci(t, 0, 1)
        assert e_rot(p.T_cj_ci, gt) < 1e-5 and np.linalg.norm(p.T_cj_ci[:3, 3] - gt[:3, 3]) < 1e-4
        assert B[t].bytes_pair > 0 and not B[t].request_skipped and B[t].source == "direct"
    # 18 steps later the propagation model's sigma is above the thresholds: it asks again
    assert P[25].gate_open and not P[25].request_skipped and P[25].bytes_pair > 0 and P[25].source == "direct"
    assert P[25].anchor_verdict == "accepted"
    sent = lambda rs: sum(r.bytes_sent.get("reply", 0) + r.bytes_sent.get("request", 0) for x in rs for r in x.robots)
    assert sent(results) < sent(base)
    # the paper's configuration never skips: every open gate requested
    assert not any(p.request_skipped for res in base for p in res.pairs)
    assert all(p.bytes_pair > 0 for res in base for p in res.pairs if p.gate_open)


def test_pays_with_zero_thresholds_and_always_are_the_papers_records_where_the_gate_opens():
    _, base, _ = _run({"mode": "gate"})
    _, zero, _ = _run({"mode": "pays", "max_steps": 0, "max_sigma_rot_rad": 0.0, "max_sigma_pos_m": 0.0})
    rows = lambda rs: [p.as_row() for res in rs for p in res.pairs]
    for a, b in zip(rows(base), rows(zero)):
        assert a.keys() == b.keys()
        assert all(a[k] == b[k] or (a[k] != a[k] and b[k] != b[k]) for k in a), a["step"]
    _, always, _ = _run({"mode": "always"})
    assert all(p.bytes_pair > 0 for res in always for p in res.pairs)  # gate or not
    assert sum(p.source == "direct" for res in always for p in res.pairs) > \
        sum(p.source == "direct" for res in base for p in res.pairs)


def test_graph_backend_reads_the_graphs_sigma_instead_of_the_propagation_model(monkeypatch):
    # a propagation model that always says "uncertain": the switch asks, the graph's own sigma does not
    monkeypatch.setattr(policy_mod, "ROT_SIGMA0_RAD", 10.0)
    policy = {"mode": "pays", "max_sigma_pos_m": 1.0}  # graph: 0.46 m at step 7
    _, _, S = _run(policy)
    assert not S[8].request_skipped and S[8].bytes_pair > 0
    _, _, G = _run(policy, backend="graph")
    assert np.isfinite(G[7].cov).all()
    assert G[8].request_skipped and G[8].bytes_pair == 0 and G[8].source == "propagated"
    # and a threshold below the graph's sigma asks again
    _, _, H = _run({"mode": "pays", "max_sigma_rot_rad": 1e-9}, backend="graph")
    assert not H[8].request_skipped and H[8].bytes_pair > 0


def test_backoff_rule_known_answers():
    conf = PolicyConfig(mode="pays", miss_limit=3, miss_backoff_steps=3)
    missed = PairView(anchored=False, misses=3, steps_since_ask=1)
    assert decide(conf, True, missed) == (False, "backoff")
    assert decide(conf, True, dataclasses.replace(missed, steps_since_ask=2)) == (False, "backoff")
    assert decide(conf, True, dataclasses.replace(missed, steps_since_ask=3)) == (True, "no-anchor")
    assert decide(conf, True, dataclasses.replace(missed, misses=2)) == (True, "no-anchor")
    # an anchored pair whose anchor is old backs off alike; a fresh one needs no request anyway
    assert decide(conf, True, dataclasses.replace(FRESH, steps_since=40, misses=5, steps_since_ask=1)) == \
        (False, "backoff")
    assert decide(conf, True, dataclasses.replace(FRESH, steps_since=40, misses=5, steps_since_ask=4)) == \
        (True, "stale")
    # off by default and in the paper's mode; "always" asks whatever
    assert decide(PAYS, True, missed) == (True, "no-anchor")
    assert decide(dataclasses.replace(conf, mode="gate"), True, missed) == (True, "gate")
    assert decide(dataclasses.replace(conf, mode="always"), False, missed) == (True, "always")
    assert [backoff_steps(conf, m) for m in range(6)] == [0, 0, 0, 3, 3, 3]  # a constant wait


def test_agent_backs_off_from_an_open_gate_whose_images_place_nothing():
    world = make_world(2, 40, seed=1)
    early = lambda current, key: len(key) == 3 and key[1] < 5  # a collaborator's image places from step 5 on

    def run(policy):
        cfg = AlgorithmConfig().override({"scale.min_pixels": 20, "policy": policy, "gate.tau": -1.0})  # the gate opens at every step
        team = Team(world.robot_ids, OverlapDescriptor(world), GTBackbone(world, seed=1, invalid=early),
                    SensorDepthDouble(), cfg)
        return {res.step: next(p for p in res.pairs if p.ego == "r0" and p.other == "r1")
                for res in team.run_encounter(world.to_encounter())}

    P = run({"mode": "pays", "miss_limit": 3, "miss_backoff_steps": 3})
    B = run({"mode": "pays"})
    assert all(P[t].gate_open for t in P)
    # nothing places before step 5: three requests that place nothing, then one every third step
    asked = [t for t in range(10) if P[t].bytes_pair > 0]
    assert asked[:4] == [0, 1, 2, 5] and all(P[t].request_skipped for t in (3, 4))
    assert all(B[t].bytes_pair > 0 for t in range(8))  # without back-off: every step until verified
    # the image of step 5 places: the pair asks at every step again until its anchor is verified
    assert P[5].source == "direct" and [P[t].anchor_verdict for t in (5, 6, 7)] == ["unverified", "unverified",
                                                                                   "verified"]
    assert sum(p.bytes_pair > 0 for p in P.values()) < sum(p.bytes_pair > 0 for p in B.values())



NEW_RULES = {"miss_limit": 3, "miss_backoff_steps": 3, "unanchored_backoff_steps": 2, "backoff_pending_exempt": True,
             "recheck_rot_rad": 0.03, "recheck_limit": 2}


def test_after_request_logs_misses_and_what_set_the_anchor():
    conf = PolicyConfig(mode="pays", recheck_rot_rad=0.03)
    log = after_request(conf, None, 4, placed=False)
    assert log == AskLog(4, 1, hard_misses=1) and after_request(conf, log, 5, placed=False).misses == 2
    # a placed estimate that set the anchor: misses reset, its disagreement kept
    log = after_request(conf, log, 6, True, "verified", 0.05)
    assert (log.step, log.misses, log.anchor_rot_rad, log.rechecks) == (6, 0, 0.05, 1)
    log = after_request(conf, log, 7, True, "accepted", 0.04)
    assert log.rechecks == 2
    # rejected or unverified: the anchor stays, and so does what set it
    kept = after_request(conf, log, 8, True, "rejected", 0.3)
    assert (kept.anchor_rot_rad, kept.rechecks, kept.misses) == (0.04, 2, 0)
    # two estimates in a row that agree end the streak
    assert after_request(conf, log, 9, True, "accepted", 0.01).rechecks == 0
    assert after_request(PAYS, log, 9, True, "accepted", 0.5).rechecks == 0  # the rule off: no streak
    assert AskLog(3, 2, 0.1, 1, 5).view(10) == {"misses": 2, "hard_misses": 5, "steps_since_ask": 7,
                                                "anchor_rot_rad": 0.1, "rechecks": 1}


def test_hard_misses_run_on_through_placements_that_set_no_anchor():
    conf = PolicyConfig()
    log = after_request(conf, after_request(conf, None, 1, placed=False), 2, placed=False)
    assert (log.misses, log.hard_misses) == (2, 2)
    # a rejected or unverified placement: misses restart, hard_misses neither count it nor restart
    for verdict in ("rejected", "unverified", ""):
        kept = after_request(conf, log, 3, True, verdict, 0.4)
        assert (kept.misses, kept.hard_misses) == (0, 2)
        assert after_request(conf, kept, 4, placed=False).hard_misses == 3
    # an estimate that set the anchor restarts both
    assert after_request(conf, log, 3, True, "verified", 0.01).hard_misses == 0


def test_recheck_and_backoff_rules_known_answers():
    conf = PolicyConfig(mode="pays", recheck_rot_rad=0.03, recheck_limit=2)
    doubt = dataclasses.replace(FRESH, anchor_rot_rad=0.05, rechecks=1)
    assert decide(PAYS, True, doubt) == (False, "anchor-fresh")  # off by default
    assert decide(conf, True, doubt) == (True, "recheck")
    assert decide(conf, True, dataclasses.replace(doubt, rechecks=2)) == (True, "recheck")
    assert decide(conf, True, dataclasses.replace(doubt, rechecks=3)) == (False, "anchor-fresh")  # limit reached
    assert decide(conf, True, dataclasses.replace(doubt, anchor_rot_rad=0.02)) == (False, "anchor-fresh")
    assert decide(conf, False, doubt) == (False, "gate-closed")  # only through an open gate
    assert decide(dataclasses.replace(conf, recheck_limit=0), True, dataclasses.replace(doubt, rechecks=2)) == \
        (False, "anchor-fresh")  # a limit of 0: one recheck
    # a pair whose candidates wait to verify does not back off with backoff_pending_exempt
    back = PolicyConfig(mode="pays", miss_limit=3, miss_backoff_steps=3)
    waiting = PairView(anchored=False, pending=True, misses=3, steps_since_ask=1)
    assert decide(back, True, waiting) == (False, "backoff")
    assert decide(dataclasses.replace(back, backoff_pending_exempt=True), True, waiting) == (True, "no-anchor")
    assert decide(dataclasses.replace(back, backoff_pending_exempt=True), True,
                  dataclasses.replace(waiting, pending=False)) == (False, "backoff")
    # a wait of its own for a pair without an anchor; an anchored pair keeps miss_backoff_steps
    own = dataclasses.replace(back, unanchored_backoff_steps=2)
    assert [backoff_steps(own, 3, anchored) for anchored in (False, True)] == [2, 3]
    lost = dataclasses.replace(waiting, pending=False, steps_since_ask=2)
    assert decide(own, True, lost) == (True, "no-anchor") and decide(back, True, lost) == (False, "backoff")
    assert decide(own, True, dataclasses.replace(FRESH, steps_since=40, misses=3, steps_since_ask=2)) == \
        (False, "backoff")
    # the paper's mode reads none of them
    assert decide(PolicyConfig(**NEW_RULES), True, doubt) == (True, "gate")
    assert decide(PolicyConfig(**NEW_RULES), False, doubt) == (False, "gate-closed")


def test_gate_mode_records_are_unchanged_by_the_new_rules():
    rows = lambda rs: [p.as_row() for res in rs for p in res.pairs]
    _, base, _ = _run({"mode": "gate"})
    _, same, _ = _run({"mode": "gate", **NEW_RULES})
    for a, b in zip(rows(base), rows(same), strict=True):
        assert a.keys() == b.keys()
        assert all(a[k] == b[k] or (a[k] != a[k] and b[k] != b[k]) for k in a), a["step"]


def test_agent_rechecks_an_anchor_its_estimate_disagreed_with():
    # the GT doubles' estimates agree to ~1e-6 rad: a threshold below that makes every anchor "disputed"
    _, _, P = _run({"mode": "pays"})
    _, _, R = _run({"mode": "pays", "recheck_rot_rad": 1e-12, "recheck_limit": 1})
    assert P[8].request_skipped and R[7].anchor_verdict == "verified"
    # verified at 7 disagreeing by more than the threshold: one recheck at 8 (accepted), then the streak
    # (2 > limit 1) stops asking
    assert not R[8].request_skipped and R[8].bytes_pair > 0 and R[8].anchor_verdict == "accepted"
    assert R[9].request_skipped and R[9].bytes_pair == 0


def test_try_hard_while_unanchored_backing_off_by_powers_of_two(monkeypatch):
    # the shipped schedule, one try: 0, 1, 2, 4, 8, 16, 32, then every 32
    assert [m for m in range(100) if try_hard(PairView(anchored=False, hard_misses=m))] == [
        0, 1, 2, 4, 8, 16, 32, 64, 96]
    monkeypatch.setattr(policy_mod, "HARD_TRIES", 2)
    monkeypatch.setattr(policy_mod, "HARD_BACKOFF_MAX_STEPS", 8)
    asked = [m for m in range(40) if try_hard(PairView(anchored=False, hard_misses=m))]
    # misses before the request: 0, 1 (the tries), then where misses - 1 is 1, 2, 4, 8, then every 8
    assert asked == [0, 1, 2, 3, 5, 9, 17, 25, 33]
    assert not any(try_hard(PairView(anchored=True, hard_misses=m)) for m in range(40))
    # the schedule reads hard_misses, not the misses in a row that a placement restarts
    assert not try_hard(PairView(anchored=False, misses=0, hard_misses=4))


def test_skip_for_shared_known_answers(monkeypatch):
    monkeypatch.setattr(policy_mod, "SHARED_RETRY_STEPS", 4)
    base = dict(anchored=False, misses=2, steps_since_shared=1, steps_since_ask=1)
    assert skip_for_shared(PairView(**base))
    assert not skip_for_shared(PairView(**{**base, "misses": 1}))  # its own images may still place
    assert not skip_for_shared(PairView(**{**base, "steps_since_shared": 2}))  # the peer stopped sharing
    assert not skip_for_shared(PairView(**{**base, "steps_since_ask": 4}))  # time to look again

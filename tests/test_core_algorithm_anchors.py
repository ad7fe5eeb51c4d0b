"""cerpe.algorithm.anchors on its own: known answers and random round trips in SE(3)."""
from __future__ import annotations

import numpy as np
import pytest

from cerpe.algorithm import anchors as anchors_mod
from cerpe.algorithm.anchors import (
    Anchor,
    AnchorConfig,
    PairAnchors,
    consensus,
    consistent,
    disagreement,
    tolerance,
)
from cerpe.geometry import make_se3, paper_T_ij, random_se3, rotation_angle, so3_exp

CONF = AnchorConfig(rot_tol_rad=0.1, trans_tol_m=0.3, replace_after=3, max_unverified_steps=3, candidate_steps=10,
                    verify_support=1, verify_fraction=0.0, max_odo_rot_step=0.0)
# the module's constants, at values that make the known answers below simple
CONSTANTS = {"ROT_DRIFT_PER_STEP": 0.01, "TRANS_DRIFT_FRAC": 0.1, "TRANS_REL": 0.0, "AGREE_ROT_RAD": 0.05,
             "AGREE_TRANS_M": 0.1}


@pytest.fixture(autouse=True)
def _constants(monkeypatch):
    for name, value in CONSTANTS.items():
        monkeypatch.setattr(anchors_mod, name, value)


class Pair:
    """Two robots on random trajectories in one world; each odometry starts at identity."""

    def __init__(self, seed: int, n: int = 30) -> None:
        rng = np.random.default_rng(seed)
        self.W = {r: [random_se3(rng, 20.0)] for r in "ij"}
        for r in "ij":
            for _ in range(n - 1):
                step = make_se3(so3_exp(rng.normal(0, 0.05, 3)), rng.normal(0, 0.5, 3))
                self.W[r].append(self.W[r][-1] @ step)

    def X(self, r: str, t: int) -> np.ndarray:
        return np.linalg.inv(self.W[r][0]) @ self.W[r][t]

    def odo(self, r: str, t: int) -> float:
        return float(sum(np.linalg.norm(self.W[r][k + 1][:3, 3] - self.W[r][k][:3, 3]) for k in range(t)))

    def est(self, t: int, error: np.ndarray | None = None) -> Anchor:
        T = paper_T_ij(self.W["i"][t], self.W["j"][t])
        if error is not None:  # on the right: camera i turned about its centre, translation unchanged
            T = T @ error
        return Anchor(t, T, self.X("i", t), self.X("j", t), self.odo("i", t), self.odo("j", t))


def rot(angle: float, axis=(0.0, 1.0, 0.0)) -> np.ndarray:
    return make_se3(so3_exp(angle * np.asarray(axis)), np.zeros(3))


@pytest.mark.parametrize("seed", range(5))
def test_true_estimates_agree_after_propagation_over_any_gap(seed):
    p = Pair(seed)
    for a, b in [(0, 1), (3, 17), (5, 29)]:
        r, t = disagreement(p.est(a), p.est(b))
        assert r < 1e-7 and t < 1e-6
    # an error of known size comes out as that size, whatever the gap
    r, t = disagreement(p.est(2), p.est(9, rot(0.5)))
    assert r == pytest.approx(0.5, abs=1e-9)


def test_tolerance_grows_with_steps_travel_and_distance(monkeypatch):
    p = Pair(1)
    a = p.est(0)
    r1, t1 = tolerance(CONF, a, p.est(1))
    r9, t9 = tolerance(CONF, a, p.est(9))
    assert r1 == pytest.approx(0.11) and r9 == pytest.approx(0.19)
    assert t1 == pytest.approx(0.3 + 0.1 * (p.odo("i", 1) + p.odo("j", 1)))
    assert t9 > t1
    b = p.est(1)
    without = tolerance(CONF, a, b)[1]
    monkeypatch.setattr(anchors_mod, "TRANS_REL", 0.5)
    assert tolerance(CONF, a, b)[1] == pytest.approx(without + 0.5 * np.linalg.norm(b.T_cj_ci[:3, 3]))
    b.metric = False  # no metric depth: translations are not compared
    assert tolerance(CONF, a, b)[1] == np.inf


def test_wrong_estimate_is_rejected_and_a_consistent_one_accepted():
    p = Pair(2)
    pa = PairAnchors(CONF, anchor=p.est(0))
    check = pa.offer(p.est(2, rot(0.5)))
    assert check.verdict == "rejected" and check.against == 0 and check.rot_rad == pytest.approx(0.5)
    assert pa.anchor.step == 0
    check = pa.offer(p.est(3, rot(0.05)))  # within 0.1 + 3 * 0.01
    assert check.verdict == "accepted" and pa.anchor.step == 3 and not pa.challengers
    assert pa.carried(7) == (pa.anchor, True)


def test_a_weak_consistent_estimate_keeps_the_anchor_and_a_weak_wrong_one_is_judged_as_any():
    import dataclasses

    p = Pair(2)
    conf = dataclasses.replace(CONF, min_inliers=40)
    pa = PairAnchors(conf, anchor=p.est(0))

    def est(t, inliers, error=None):
        return dataclasses.replace(p.est(t, error), inliers=inliers)

    check = pa.offer(est(1, 39, rot(0.05)))  # agrees, on 39 inliers: weak, the anchor stays
    assert check.verdict == "weak" and check.against == 0 and pa.anchor.step == 0 and not pa.challengers
    assert pa.carried(2) == (pa.anchor, True)
    assert pa.offer(est(2, 40)).verdict == "accepted" and pa.anchor.step == 2  # 40: enough
    assert pa.offer(est(3, -1)).verdict == "accepted" and pa.anchor.step == 3  # unknown inliers: no rule
    assert pa.offer(est(4, 10, rot(0.5))).verdict == "rejected" and pa.anchor.step == 3  # disagrees: rejected
    assert len(pa.challengers) == 1
    off = PairAnchors(dataclasses.replace(CONF, min_inliers=0), anchor=p.est(0))  # 0: off
    assert off.offer(est(1, 5)).verdict == "accepted"
    fresh = PairAnchors(conf)  # without an anchor the rule does not apply: candidates verify as before
    assert fresh.offer(est(1, 5)).verdict == "unverified"
    assert fresh.offer(est(2, 5)).verdict == "verified" and fresh.anchor.step == 2


def test_persistent_disagreement_replaces_the_anchor():
    p = Pair(3)
    wrong = rot(0.6, (1.0, 0.0, 0.0))
    pa = PairAnchors(CONF, anchor=p.est(0, wrong))  # a wrong anchor; then right estimates keep coming
    assert [pa.offer(p.est(t)).verdict for t in (1, 2)] == ["rejected", "rejected"]
    assert pa.anchor.step == 0
    check = pa.offer(p.est(3))
    assert check.verdict == "replaced" and pa.anchor.step == 3
    assert pa.offer(p.est(4)).verdict == "accepted"


def test_rejections_that_disagree_with_each_other_do_not_replace():
    p = Pair(4)
    pa = PairAnchors(CONF, anchor=p.est(0))
    angles = [0.5, -0.5, 0.8, -0.8, 1.1, -1.1]
    verdicts = [pa.offer(p.est(t, rot(a))).verdict for t, a in enumerate(angles, start=1)]
    assert verdicts == ["rejected"] * 6 and pa.anchor.step == 0


def test_challengers_too_far_apart_do_not_replace():
    p = Pair(5, n=40)
    pa = PairAnchors(CONF, anchor=p.est(0))
    for t in (1, 15, 30):  # agree with each other, but more than candidate_steps apart
        assert pa.offer(p.est(t, rot(1.0))).verdict == "rejected"


def test_unverified_is_carried_for_max_unverified_steps_only():
    p = Pair(6)
    pa = PairAnchors(CONF)
    assert pa.offer(p.est(5)).verdict == "unverified"
    for t in (6, 7, 8):
        a, verified = pa.carried(t)
        assert a is not None and a.step == 5 and not verified
    assert pa.carried(9) == (None, False)


def test_a_later_agreeing_estimate_verifies_and_a_disagreeing_one_does_not():
    p = Pair(7)
    pa = PairAnchors(CONF)
    assert pa.offer(p.est(5, rot(0.5))).verdict == "unverified"
    check = pa.offer(p.est(6))
    assert check.verdict == "unverified" and check.against == 5 and check.rot_rad == pytest.approx(0.5, abs=0.02)
    check = pa.offer(p.est(8, rot(0.02)))  # agrees with step 6 (propagated), not with step 5
    assert check.verdict == "verified" and check.against == 6 and pa.anchor.step == 8
    assert not pa.candidates


def test_candidates_older_than_candidate_steps_do_not_verify():
    p = Pair(8, n=40)
    pa = PairAnchors(CONF)
    pa.offer(p.est(2))
    assert pa.offer(p.est(2 + CONF.candidate_steps + 1)).verdict == "unverified"
    assert [c.step for c in pa.candidates] == [13]


def test_two_registrations_of_one_step_verify_at_once_when_they_agree():
    p = Pair(9)
    e = p.est(4)
    close = Anchor(4, e.T_cj_ci @ rot(0.03), e.X_i, e.X_j)
    far = Anchor(4, e.T_cj_ci @ rot(0.2), e.X_i, e.X_j)
    pa = PairAnchors(CONF)
    assert pa.offer(e, [far]).verdict == "unverified"
    pa = PairAnchors(CONF)
    check = pa.offer(e, [far, close])
    assert check.verdict == "verified" and check.rot_rad == pytest.approx(0.03) and pa.anchor is e


def test_consistent_is_symmetric_in_rotation_for_random_errors():
    rng = np.random.default_rng(0)
    p = Pair(10)
    for _ in range(20):
        a, b = sorted(rng.choice(30, 2, replace=False))
        err = make_se3(so3_exp(rng.normal(0, 0.3, 3)), rng.normal(0, 0.5, 3))
        ok, r, t = consistent(CONF, p.est(a), p.est(b, err))
        r2, _ = disagreement(p.est(b, err), p.est(a))
        assert r == pytest.approx(r2, abs=1e-9)
        assert ok == (r <= CONF.rot_tol_rad + CONSTANTS['ROT_DRIFT_PER_STEP'] * (b - a) and t <= tolerance(
            CONF, p.est(a), p.est(b, err))[1])


def test_an_interleaved_outlier_does_not_stop_a_replacement():
    p = Pair(11)
    pa = PairAnchors(CONF, anchor=p.est(0, rot(0.8)))  # replace_after = 3
    verdicts = [pa.offer(p.est(t, rot(1.2) if t == 2 else None)).verdict for t in (1, 2, 3, 4)]
    assert verdicts == ["rejected", "rejected", "rejected", "replaced"] and pa.anchor.step == 4


def test_verify_support_asks_for_that_many_agreeing_candidates():
    import dataclasses

    p = Pair(12)
    pa = PairAnchors(dataclasses.replace(CONF, verify_support=2))
    assert [pa.offer(p.est(t)).verdict for t in (5, 6)] == ["unverified", "unverified"]
    check = pa.offer(p.est(8))
    assert check.verdict == "verified" and check.against == 6 and pa.anchor.step == 8
    # two registrations of one step that agree still verify at once
    pa = PairAnchors(dataclasses.replace(CONF, verify_support=2))
    e = p.est(9)
    assert pa.offer(e, [Anchor(9, e.T_cj_ci @ rot(0.01), e.X_i, e.X_j)]).verdict == "verified"


def test_without_report_unverified_nothing_unverified_is_carried():
    import dataclasses

    p = Pair(13)
    pa = PairAnchors(dataclasses.replace(CONF, report_unverified=False))
    assert pa.offer(p.est(5)).verdict == "unverified"
    assert pa.carried(5) == (None, False) and pa.carried(6) == (None, False)
    check = pa.offer(p.est(6, rot(0.02)))  # verify_support = 1: agrees with step 5
    assert check.verdict == "verified" and check.against == 5
    a, verified = pa.carried(7)
    assert a is not None and a.step == 6 and verified


def test_verify_fraction_asks_most_recent_candidates_to_agree():
    """Two estimates that disagree with everything (0.5 rad either way), then right ones: with
    ``verify_fraction`` 0.6 a right estimate is verified only once the agreeing candidates are at
    least 60 % of those of the last ``candidate_steps`` steps; with 0, by the first agreeing one."""
    import dataclasses

    p = Pair(14)
    plan = [(2, rot(0.5)), (3, rot(-0.5)), (4, None), (5, None), (6, None), (7, None)]
    for fraction, want in ((0.6, ["unverified"] * 5 + ["verified"]),
                           (0.0, ["unverified"] * 3 + ["verified", "accepted", "accepted"])):
        pa = PairAnchors(dataclasses.replace(CONF, verify_fraction=fraction))
        assert [pa.offer(p.est(t, e)).verdict for t, e in plan] == want, fraction
    pa = PairAnchors(dataclasses.replace(CONF, verify_fraction=0.6))
    checks = [pa.offer(p.est(t, e)) for t, e in plan]
    assert checks[-1].against == 6 and pa.anchor.step == 7  # 3 of 5 candidates (4, 5, 6) agree


@pytest.mark.parametrize("value", [-0.1, 1.5, float("nan")])
def test_config_refuses_a_verify_fraction_outside_0_1(value):
    from cerpe.algorithm import AlgorithmConfig
    from cerpe.knobs import KnobError

    with pytest.raises(KnobError, match="anchors.verify_fraction"):
        AlgorithmConfig().override({"anchors.verify_fraction": value})
    assert AlgorithmConfig().override({"anchors.verify_fraction": 0.5, "anchors.report_unverified": False}).anchors == \
        AnchorConfig(verify_fraction=0.5, report_unverified=False)


def test_an_odometry_jump_makes_the_pair_forget_its_anchor_and_candidates():
    import dataclasses

    p = Pair(15)
    conf = dataclasses.replace(CONF, max_odo_rot_step=1.0)
    pa = PairAnchors(conf, anchor=p.est(0))
    pa.offer(p.est(1))
    for t in range(2, 6):  # smooth odometry (about 0.1 rad per step): nothing forgotten
        assert pa.track(t, p.X("i", t), p.X("j", t)) == 0.0
    assert pa.anchor.step == 1
    jumped = p.X("j", 6) @ rot(1.5)  # j's track lost at step 6: turned 1.5 rad in one step
    turn = pa.track(6, p.X("i", 6), jumped)
    assert turn == pytest.approx(float(rotation_angle((np.linalg.inv(p.X("j", 5)) @ jumped)[:3, :3])))
    assert turn > 1.0 and pa.anchor is None and not pa.candidates and not pa.challengers
    assert pa.carried(6) == (None, False)
    # over a gap the turn counts per step; the check is off with max_odo_rot_step 0
    pa = PairAnchors(conf, anchor=p.est(0))
    pa.track(0, p.X("i", 0), p.X("j", 0))
    assert pa.track(3, p.X("i", 0) @ rot(1.5), p.X("j", 0)) == 0.0 and pa.anchor is not None
    pa = PairAnchors(CONF, anchor=p.est(0))
    pa.track(5, p.X("i", 5), p.X("j", 5))
    assert pa.track(6, p.X("i", 6), jumped) == 0.0 and pa.anchor is not None


def moved(p: Pair, t: int, d) -> Anchor:
    """Step ``t``'s estimate with camera i placed ``d`` metres off in the world: right rotation, wrong
    translation; estimates moved by one ``d`` agree with each other after propagation."""
    e = p.est(t)
    G = make_se3(np.eye(3), np.asarray(d, float))
    e.T_cj_ci = paper_T_ij(G @ p.W["i"][t], p.W["j"][t])
    return e


def test_moved_estimates_keep_the_rotation_and_agree_with_each_other_only():
    p = Pair(16)
    r, t = disagreement(p.est(2), moved(p, 3, (15.0, 0.0, 0.0)))
    assert r < 1e-7 and t == pytest.approx(15.0)
    r, t = disagreement(moved(p, 2, (15.0, 0.0, 0.0)), moved(p, 5, (15.0, 0.0, 0.0)))
    assert r < 1e-7 and t < 1e-6


def test_a_translation_outlier_with_the_right_rotation_is_rejected_and_blocks_nothing():
    """Two right estimates and one 15 m off in translation with the right rotation: the two verify
    each other (verify_support 1), the outlier is dropped (rejected), even with verify_fraction 1."""
    import dataclasses

    p = Pair(17)
    for fraction in (0.0, 1.0):
        pa = PairAnchors(dataclasses.replace(CONF, verify_fraction=fraction))
        assert pa.offer(p.est(2)).verdict == "unverified"
        check = pa.offer(moved(p, 3, (15.0, 0.0, 0.0)))
        assert check.verdict == "unverified" and check.trans_m == pytest.approx(15.0)
        check = pa.offer(p.est(4))
        assert check.verdict == "verified" and check.against == 2 and check.dropped == (3,), fraction
        assert pa.anchor.step == 4 and not pa.candidates
    # an outlier in rotation does count against the group: 1 of 2 others agree, below 1.0
    pa = PairAnchors(dataclasses.replace(CONF, verify_fraction=1.0))
    assert [pa.offer(e).verdict for e in (p.est(2), p.est(3, rot(0.5)), p.est(4))] == ["unverified"] * 3


def test_translation_outliers_do_not_block_a_group_under_the_default_support_and_fraction():
    """verify_support 2, verify_fraction 0.5 (the defaults): one right estimate, three 15 m off each a
    different way (right rotation), two right ones: the newest right one is verified against the right
    ones, the three outliers are rejected. Before, 2 agreeing of 5 candidates (0.4 < 0.5) verified nothing."""
    import dataclasses

    p = Pair(18)
    pa = PairAnchors(dataclasses.replace(CONF, verify_support=2, verify_fraction=0.5))
    offers = [p.est(2), moved(p, 3, (15.0, 0.0, 0.0)), moved(p, 4, (-15.0, 0.0, 0.0)),
              moved(p, 5, (0.0, 15.0, 0.0)), p.est(6)]
    assert [pa.offer(e).verdict for e in offers] == ["unverified"] * 5
    check = pa.offer(p.est(7))
    assert check.verdict == "verified" and check.against == 6 and check.dropped == (3, 4, 5)
    assert pa.anchor.step == 7 and not pa.candidates


def test_two_groups_as_large_verify_nothing_until_one_grows():
    """Two right estimates and two that agree with each other 15 m off: two hypotheses, nothing
    verified; a third right one decides (verify_support 1). Indices into the pool, oldest first."""
    p = Pair(19)
    d = (0.0, 0.0, 15.0)
    pool = [p.est(2), moved(p, 3, d), moved(p, 4, d), p.est(5)]
    assert consensus(CONF, pool) is None
    assert consensus(CONF, [*pool, p.est(6)]) == [0, 3, 4]
    assert consensus(CONF, pool[:3]) == [1, 2]  # {3, 4}: larger than {2}


def test_an_estimate_that_completes_the_rotation_support_is_rejected_and_the_group_verified():
    """verify_support 1, verify_fraction 0.6: right estimates at 2 and 4 with one 0.5 rad off between
    (1 of 2 others agree in rotation: too few); a 15 m translation outlier with the right rotation
    makes it 2 of 3: the group {2, 4} verifies, its newest is the anchor, the outlier is rejected
    against it and step 3 is dropped."""
    import dataclasses

    p = Pair(20)
    pa = PairAnchors(dataclasses.replace(CONF, verify_fraction=0.6))
    assert [pa.offer(e).verdict for e in (p.est(2), p.est(3, rot(0.5)), p.est(4))] == ["unverified"] * 3
    check = pa.offer(moved(p, 5, (15.0, 0.0, 0.0)))
    assert check.verdict == "rejected" and check.against == 4 and check.dropped == (3,)
    assert check.rot_rad < 1e-6 and check.trans_m == pytest.approx(15.0)
    assert pa.anchor.step == 4 and pa.carried(5) == (pa.anchor, True)

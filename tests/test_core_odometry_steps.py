"""The odometry's step-length rule (cerpe.scale.StepLengthRule): known answers, then a team run
with one injected collapsed step (held and counted) and a consistent one (unchanged)."""
from __future__ import annotations

import numpy as np
import pytest

from cerpe.algorithm import DEGRADATIONS, AlgorithmConfig, Team
from cerpe.knobs import KnobError
from cerpe.geometry import make_se3, se3_inverse
from cerpe.scale import ScaleError, StepLengthRule, step_ratios
from gt_backbone import GTBackbone, OverlapDescriptor, SensorDepthDouble, make_world


# ----------------------------------------------------------------------------- the rule
def test_rule_known_answers():
    rule = StepLengthRule(max_ratio=2.0, max_accel_mps2=5.0, noise_m=0.05)
    # a car at 8 m/s, 10 Hz: 1.7 m/s one step later is no braking (61 m/s^2)
    assert not rule.plausible(0.17, 0.1, 8.0, 0.1)
    assert rule.plausible(1.9, 0.1, 8.0, 0.1)  # rises are never held (a collapsed reference recovering)
    assert rule.plausible(0.45, 0.1, 8.0, 0.1)  # 4.5 m/s: within the ratio
    # bound after held steps: 6.3 m/s off needs 5 * t + 0.5 >= 6.3, t >= 1.16 s
    assert not rule.plausible(0.17, 0.1, 8.0, 1.1)
    assert rule.plausible(0.17, 0.1, 8.0, 1.2)
    # slow platforms and short steps: 2 cm steps may halve or vanish (noise floor)
    assert rule.plausible(0.001, 0.1, 0.2, 0.1)
    assert rule.plausible(0.002, 1 / 30, 0.6, 1 / 30)
    # nothing to compare with, or off
    assert rule.plausible(0.17, 0.1, None, 0.0)
    assert StepLengthRule(max_accel_mps2=0.0).plausible(0.17, 0.1, 8.0, 0.1)
    # the reference: median of the last `window` accepted speeds, once there are `min_history`
    rule = StepLengthRule(window=3, min_history=2)
    assert rule.reference([8.0]) is None
    assert rule.reference([1.0, 8.0, 9.0, 7.0]) == 8.0  # the last 3; an older slow step does not count
    assert rule.reference([8.0, 30.0, 7.0]) is None  # not steady: no speed to hold


@pytest.mark.parametrize("kw", [{"max_ratio": 1.0}, {"max_accel_mps2": -1.0}, {"noise_m": float("nan")},
                                {"window": 2, "min_history": 3}])
def test_rule_refuses_bad_values(kw):
    with pytest.raises(ScaleError):
        StepLengthRule(**kw)
    if "max_accel_mps2" in kw:  # the rule's one knob
        with pytest.raises(KnobError, match="odometry.max_accel_mps2"):
            AlgorithmConfig().override({"odometry.max_accel_mps2": kw["max_accel_mps2"]})


def test_step_ratios_figures():
    s = step_ratios(np.array([1.0, 0.2, 1.0, 3.0, 0.0]), np.array([1.0, 1.0, 1.0, 1.0, 0.0]))
    assert s["n"] == 4 and s["median"] == pytest.approx(1.0) and s["outside"] == 2
    assert step_ratios(np.array([]), np.array([]))["n"] == 0


# ----------------------------------------------------------------------------- in the team
COLLAPSED = 12


def _collapse(world, robot: str, step: int, frac: float = 0.2):
    """A placement of ``robot``'s view at ``step``, as current view, ``frac`` of the way from its
    previous pose (a collapsed step: a moving object taken for the scene)."""
    i = world.index(robot)
    T_prev, T_cur = world.T_world_cam[i, step - 1], world.T_world_cam[i, step]
    target = T_cur.copy()
    target[:3, 3] = T_prev[:3, 3] + frac * (T_cur[:3, 3] - T_prev[:3, 3])
    P = se3_inverse(T_cur) @ target

    def perturb(current, via, key):
        return P if via is None and key == current == (robot, step) else None

    return perturb


def _run(world, config: AlgorithmConfig, perturb=None):
    bb = GTBackbone(world, unit_range=(1.0, 1.0), claim_metric=True, seed=1, perturb=perturb)
    team = Team(world.robot_ids, OverlapDescriptor(world), bb, SensorDepthDouble(), config)
    return list(team.run_encounter(world.to_encounter()))


def _odometry(results, robot: str) -> np.ndarray:
    return np.stack([r.T_odom_cam for res in results for r in res.robots if r.robot == robot])


def _step_lengths(X: np.ndarray) -> np.ndarray:
    return np.array([np.linalg.norm((se3_inverse(X[k - 1]) @ X[k])[:3, 3]) for k in range(1, len(X))])


def test_collapsed_step_is_held_and_counted():
    world = make_world(2, 20, seed=4)
    cfg = AlgorithmConfig().override({"scale.min_pixels": 20})
    perturb = _collapse(world, "r0", COLLAPSED)
    held = _run(world, cfg, perturb)
    free = _run(world, AlgorithmConfig().override({"scale.min_pixels": 20, "odometry.max_accel_mps2": 0.0}), perturb)
    true = _step_lengths(np.stack([world.gt_odometry(0, t) for t in range(world.n_steps)]))
    got, raw = _step_lengths(_odometry(held, "r0")), _step_lengths(_odometry(free, "r0"))
    k = COLLAPSED - 1  # index of step COLLAPSED's length
    assert raw[k] == pytest.approx(0.2 * true[k], rel=1e-6)  # without the rule: the collapse itself
    assert got[k] == pytest.approx(np.median(true[k - 5:k]), rel=1e-6)  # held at the median of 5 accepted
    assert got[k] == pytest.approx(true[k], rel=0.05)
    counted = {res.step: r.degradations for res in held for r in res.robots if r.robot == "r0"}
    assert counted[COLLAPSED] == ["ego:step-held"]
    assert all("ego:step-held" not in d for t, d in counted.items() if t != COLLAPSED)
    # the next step is measured from the held pose and is the true motion again
    np.testing.assert_allclose(got[k + 1:], true[k + 1:], rtol=1e-6)
    assert all(not r.degradations for res in held for r in res.robots if r.robot == "r1")
    assert "ego:step-held" in DEGRADATIONS


def test_consistent_sequence_is_unchanged():
    world = make_world(3, 20, seed=5)
    on = _run(world, AlgorithmConfig().override({"scale.min_pixels": 20}))
    off = _run(world, AlgorithmConfig().override({"scale.min_pixels": 20, "odometry.max_accel_mps2": 0.0}))
    for rid in world.robot_ids:
        np.testing.assert_allclose(_odometry(on, rid), _odometry(off, rid), atol=1e-12)
    assert not any("ego:step-held" in r.degradations for res in on for r in res.robots)


def test_held_step_grows_the_graph_sigma():
    """The pose graph counts a held step's odometry as lost: its sigma after the step is larger."""
    world = make_world(2, 20, seed=4)
    perturb = _collapse(world, "r0", COLLAPSED)
    held = _run(world, AlgorithmConfig().override({"scale.min_pixels": 20, "backend.kind": "graph"}), perturb)
    free = _run(world, AlgorithmConfig().override({"scale.min_pixels": 20, "backend.kind": "graph", "odometry.max_accel_mps2": 0.0}), perturb)

    def sigma(results, step):
        return [p.as_row()["sigma_pos_m"] for res in results if res.step == step for p in res.pairs if p.ego == "r0"][0]

    s_held, s_free = sigma(held, COLLAPSED), sigma(free, COLLAPSED)
    if not (np.isfinite(s_held) and np.isfinite(s_free)):
        pytest.skip("no graph estimate at the collapsed step in this world")
    assert s_held > s_free

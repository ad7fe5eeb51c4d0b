"""The pose-graph back end (cerpe/algorithm/graph.py, ``cerpe-graph``): known answers, robustness,
covariance behaviour, bad input, and the agent with ``backend="graph"`` next to the paper's CERPE."""
from __future__ import annotations

import dataclasses

import gtsam
import numpy as np
import pytest

from cerpe.algorithm import DEGRADATIONS, AlgorithmConfig, GraphConfig, GraphModel, Team
from cerpe.algorithm import graph as graph_mod
from cerpe.algorithm.anchors import AnchorConfig
from cerpe.reasons import known_degradation as known
from cerpe.algorithm.graph import DirectEstimate, GraphError, PairGraph, graph_model, odometry_cov
from cerpe.knobs import KnobError
from cerpe.algorithm.graph_sim import simulate_pair
from cerpe.depthsim import MonoDepthSim, SensorDepthSim
from cerpe.geometry import (e_rot, make_se3, pose_cov_in_parent, pose_cov_sigmas, random_se3, se3_adjoint,
                            so3_exp)
from gt_backbone import GTBackbone, OverlapDescriptor, SensorDepthDouble, make_world


def feed(stream, conf: GraphModel | None = None, skip_pose_j: set[int] = frozenset(), replace: dict | None = None,
         rel: float | None = None, dt_s: float | None = None):
    """Run a PairGraph over a simulated stream (its direct estimates placed on depth of relative scale
    sigma ``rel``, None: unknown; steps ``dt_s`` apart, None: no stamps); returns (graph, [GraphEstimate
    per step])."""
    g = PairGraph(conf)
    out = []
    last_j = None
    for t in range(len(stream.truth)):
        if t not in skip_pose_j:
            last_j = (t, stream.X_j[t])
        if t in (replace or {}):  # None: this step's estimate never came
            d = replace[t]
        else:
            d = DirectEstimate(t, stream.direct[t], depth_rel_sigma=rel) if t in stream.direct else None
        out.append(g.step(t, stream.X_i[t], None if last_j is None else last_j[1], -1 if last_j is None else last_j[0],
                          d, stamp_s=None if dt_s is None else t * dt_s))
    return g, out


def trace(cov: np.ndarray) -> float:
    return float(np.trace(cov))


# --------------------------------------------------------------------------- pure math
def test_adjoint_is_gtsams_and_parent_covariance_matches_sampling():
    rng = np.random.default_rng(3)
    for _ in range(5):
        T = random_se3(rng)
        np.testing.assert_allclose(se3_adjoint(T), gtsam.Pose3(T).AdjointMap(), atol=1e-12)
    # a right-perturbation covariance seen in the parent frame (ROS order): Monte Carlo check
    T = random_se3(rng, 3.0)
    L = rng.normal(size=(6, 6)) * 0.01
    C = L @ L.T + np.eye(6) * 1e-4
    xi = rng.multivariate_normal(np.zeros(6), C, size=20000)
    dt, dth = [], []
    for x in xi:
        P = T @ make_se3(so3_exp(x[:3]), x[3:])
        dt.append(P[:3, 3] - T[:3, 3])
        dth.append(T[:3, :3] @ x[:3])  # the rotation error about the parent's axes (first order)
    emp = np.cov(np.hstack([dt, dth]).T)
    np.testing.assert_allclose(pose_cov_in_parent(T, C), emp, atol=3e-5)
    pos, rot = pose_cov_sigmas(C)
    assert pos == pytest.approx(np.sqrt(np.trace(C[3:, 3:]))) and rot == pytest.approx(np.sqrt(np.trace(C[:3, :3])))


def test_an_implausible_speed_change_counts_as_a_failed_odometry_step():
    conf = GraphModel()
    T = make_se3(np.eye(3), np.array([0.3, 0.0, 0.0]))
    base = odometry_cov(conf, T, 1)
    assert np.allclose(odometry_cov(conf, T, 1, speed_change_mps2=0.9 * conf.odo_max_accel_mps2), base)
    lost = odometry_cov(conf, T, 1, lost_steps=1)
    assert np.allclose(odometry_cov(conf, T, 1, speed_change_mps2=1.1 * conf.odo_max_accel_mps2), lost)
    assert np.allclose(odometry_cov(GraphModel(odo_max_accel_mps2=0.0), T, 1, speed_change_mps2=1e3), base)


def test_an_odometry_catching_up_faster_than_1g_opens_the_walk_for_the_next_estimate():
    # dev cad seed 2002 (e02): r1's odometry under-reported its motion behind a co-moving car, then one step
    # 0.39 m and 0.07 rad wrong (far under odo_jump_rad); the graph kept the old offset, 0.06 rad off,
    # through the one direct estimate after it (here 0.12 rad against estimates of 0.01 rad noise)
    s = simulate_pair(seed=6, n_steps=40, speed_m=0.05, odo_rot=0.0005, odo_trans=0.001,
                      direct_steps=list(range(2, 17, 2)) + [17], direct_rot=0.01, direct_trans=0.02)
    s.X_j[17:] = s.X_j[17:] @ make_se3(so3_exp(np.array([0.0, 0.12, 0.0])), np.array([0.39, 0.0, 0.0]))
    base = dict(direct_rot_rad=0.01, direct_trans_m=0.02, direct_trans_rel=0.0, direct_along_factor=1.0,
                direct_depth_rel_unknown=0.0)
    errs = {}
    for name, conf, dt in (("off", GraphModel(**base, odo_max_accel_mps2=0.0), 0.1),
                           ("no stamps", GraphModel(**base), None), ("on", GraphModel(**base), 0.1)):
        _, out = feed(s, conf, dt_s=dt)
        errs[name] = [float(e_rot(out[t].T_cj_ci, s.truth[t])) for t in range(17, 40)]
    assert min(errs["off"]) > 0.08 and min(errs["no stamps"]) > 0.08  # the old offset is kept
    assert max(errs["on"]) < 3 * 0.01  # 3.9 m/s in one 0.1 s step from 0.05 m/step: the walk opens there
    # a steady robot (0.05 m per 0.1 s step, noise 1 mm) never trips it: the same estimates as without it
    s = simulate_pair(seed=6, n_steps=40, speed_m=0.05, odo_rot=0.0005, odo_trans=0.001,
                      direct_steps=list(range(2, 40, 4)), direct_rot=0.01, direct_trans=0.02)
    _, a = feed(s, GraphModel(**base), dt_s=0.1)
    _, b = feed(s, GraphModel(**base, odo_max_accel_mps2=0.0), dt_s=0.1)
    assert all(np.array_equal(x.T_cj_ci, y.T_cj_ci) for x, y in zip(a, b) if x.T_cj_ci is not None)
    # nor does odometry noise at 30 Hz (1 cm per step jitters the speed by 0.3 m/s, 9 m/s^2 per 33 ms, often
    # more): the noise margin (odo_accel_noise_sigmas per-step sigmas) keeps it from reading as acceleration
    s = simulate_pair(seed=6, n_steps=40, speed_m=0.012, odo_rot=0.0005, odo_trans=0.01,
                      direct_steps=list(range(2, 40, 4)), direct_rot=0.01, direct_trans=0.02)
    _, a = feed(s, GraphModel(**base), dt_s=1 / 30)
    _, b = feed(s, GraphModel(**base, odo_max_accel_mps2=0.0), dt_s=1 / 30)
    assert all(np.array_equal(x.T_cj_ci, y.T_cj_ci) for x, y in zip(a, b) if x.T_cj_ci is not None)
    _, c = feed(s, GraphModel(**base, odo_accel_noise_sigmas=0.0), dt_s=1 / 30)  # without the margin it would
    assert any(not np.array_equal(x.T_cj_ci, y.T_cj_ci) for x, y in zip(c, b) if x.T_cj_ci is not None)


def test_odometry_covariance_grows_with_steps_and_distance():
    conf = GraphModel()
    D = make_se3(np.eye(3), [0.0, 0.0, 1.0])
    assert trace(odometry_cov(conf, D, 1)) > trace(odometry_cov(conf, np.eye(4), 1)) > 0
    assert trace(odometry_cov(conf, np.eye(4), 4)) == pytest.approx(4 * trace(odometry_cov(conf, np.eye(4), 1)))
    assert trace(odometry_cov(conf, D, 1, lost_steps=1)) > trace(odometry_cov(conf, D, 1))


@pytest.mark.parametrize("bad", [{"window_nodes": 1}, {"direct_rot_rad": -1.0},
                                 {"kernel_k": float("nan")}, {"drift_after": -1}, {"drift_cos": 1.0},
                                 {"drift_chi2": 0.0}, {"drift_inflate": float("inf")},
                                 {"sensor_max_rel": float("nan")}, {"odo_sensor_scale": 0.0}])
def test_bad_graph_model_is_one_clear_error(bad):
    with pytest.raises(GraphError, match=next(iter(bad))):
        GraphModel(**bad)


@pytest.mark.parametrize("key, value", [("window_nodes", 1), ("kernel_k", float("nan")), ("kernel_k", 0.0),
                                        ("window_nodes", "many")])
def test_bad_graph_knob_is_one_clear_error(key, value):
    with pytest.raises(KnobError, match=f"backend.graph.{key}"):
        AlgorithmConfig().override({f"backend.graph.{key}": value})
    with pytest.raises(KnobError, match="backend.kind"):
        AlgorithmConfig().override({"backend.kind": "smoother"})
    with pytest.raises(KnobError, match="unknown key 'backend.graph.no_such'; known under backend.graph: window_nodes"):
        AlgorithmConfig().override({"backend.graph.no_such": 1})


def test_graph_model_takes_the_knobs():
    conf = AlgorithmConfig().override({"backend.graph.window_nodes": 7, "backend.graph.kernel_k": 3.0,
                                       "anchors.max_unverified_steps": 4})
    model = graph_model(conf.backend.graph, conf.anchors.max_unverified_steps)
    assert (model.window_nodes, model.kernel_k, model.max_unverified_steps) == (7, 3.0, 4)
    assert dataclasses.replace(model, window_nodes=20, kernel_k=2.0, max_unverified_steps=2) == GraphModel()


# --------------------------------------------------------------------------- the checks
def test_exact_odometry_and_two_exact_anchors_reproduce_the_truth():
    s = simulate_pair(seed=0, n_steps=40, direct_steps=[3, 20])
    _, out = feed(s)
    for t, r in enumerate(out):
        if t < 3:
            assert r.T_cj_ci is None and r.cov is None  # nothing before the first direct estimate
            continue
        np.testing.assert_allclose(r.T_cj_ci, s.truth[t], atol=1e-6)
        assert r.measured == (t in (3, 20)) and r.node_step == (3 if t < 20 else 20) and not r.degradations


def test_one_wrong_anchor_among_five_good_ones_is_down_weighted():
    noise_rot, noise_trans = 0.01, 0.02
    s = simulate_pair(seed=4, n_steps=40, odo_rot=0.0005, odo_trans=0.001, direct_steps=[4, 8, 12, 16, 20, 24],
                      direct_rot=noise_rot, direct_trans=noise_trans)
    wrong = s.truth[16] @ make_se3(so3_exp(np.array([0.0, 0.5, 0.0])), np.zeros(3))
    conf = GraphModel(direct_rot_rad=noise_rot, direct_trans_m=noise_trans, direct_trans_rel=0.0, direct_along_factor=1.0,
                       direct_depth_rel_unknown=0.0)
    _, out = feed(s, conf, replace={16: DirectEstimate(16, wrong)})
    for t in range(16, 40):  # from the wrong anchor on: within the good anchors' noise (3 sigma)
        r = out[t]
        assert float(e_rot(r.T_cj_ci, s.truth[t])) < 3 * noise_rot, t
        assert np.linalg.norm(r.T_cj_ci[:3, 3] - s.truth[t][:3, 3]) < 3 * np.sqrt(3) * noise_trans, t
    # the switch would have reported the wrong anchor itself at step 16
    assert float(e_rot(wrong, s.truth[16])) > 0.45


def _five_good_and(replace: dict, consensus: int):
    noise_rot, noise_trans = 0.01, 0.02
    s = simulate_pair(seed=4, n_steps=40, odo_rot=0.0005, odo_trans=0.001, direct_steps=[4, 8, 12, 16, 20, 24],
                      direct_rot=noise_rot, direct_trans=noise_trans)
    conf = GraphModel(direct_rot_rad=noise_rot, direct_trans_m=noise_trans, direct_trans_rel=0.0,
                       direct_along_factor=1.0, direct_depth_rel_unknown=0.0, consensus_min_support=consensus)
    g, out = feed(s, conf, replace={t: DirectEstimate(t, f(s, t)) for t, f in replace.items()})
    return s, g, [float(e_rot(r.T_cj_ci, s.truth[t])) if r.T_cj_ci is not None else np.nan for t, r in enumerate(out)]


def _turned(s, t: int) -> np.ndarray:
    """The truth with the offset between the odometry frames turned by 0.5 rad: wrong estimates made
    this way agree with each other through both odometries (as a consistently aliased match would)."""
    O = s.X_j[t] @ s.truth[t] @ np.linalg.inv(s.X_i[t])
    return np.linalg.inv(s.X_j[t]) @ O @ make_se3(so3_exp(np.array([0.0, 0.5, 0.0])), np.array([0.5, 0.0, 0.0])) @ s.X_i[t]


def test_a_wrong_first_anchor_is_left_once_the_window_agrees_on_another():
    # dev indoor seed 1 (e01 r1->r2): the first direct estimate was 0.15 rad off and the Cauchy-weighted
    # graph, started at it, kept it through four better ones; the consensus re-seeds from the new majority
    _, g, err = _five_good_and({4: _turned}, consensus=0)
    assert g.n_reseeds == 0 and min(err[4:]) > 0.4  # the robust kernel alone stays where it started
    _, g, err = _five_good_and({4: _turned}, consensus=2)
    assert g.n_reseeds == 1 and err[8] > 0.4  # one good estimate against one wrong: no majority yet
    assert max(err[12:]) < 3 * 0.01  # from the second good one on: within the good anchors' noise


def test_a_run_of_consistent_wrong_anchors_against_an_established_one_is_not_followed():
    # two wrong estimates that agree with each other (0.5 rad off the same way) after four good ones
    s, g, err = _five_good_and({20: _turned, 24: _turned}, consensus=2)
    assert g.n_reseeds == 0 and max(err[4:]) < 3 * 0.01
    # three of them against three good ones: still no majority; four against two would be followed
    s, g, err = _five_good_and({16: _turned, 20: _turned, 24: _turned}, consensus=2)
    assert g.n_reseeds == 0 and max(err[4:]) < 3 * 0.01
    s, g, err = _five_good_and({12: _turned, 16: _turned, 20: _turned, 24: _turned}, consensus=2)
    assert g.n_reseeds == 1 and min(err[20:]) > 0.4


def _under_reported(s, first: int, last: int, frac: float = 0.05):
    """The stream with robot j's odometry reporting ``frac`` of its translation over steps ``first..last-1``
    and nothing flagged (a silent odometry failure: the offset between the odometry frames drifts)."""
    X = s.X_j.copy()
    for t in range(1, len(X)):
        D = np.linalg.inv(s.X_j[t - 1]) @ s.X_j[t]
        if first <= t < last:
            D = make_se3(D[:3, :3], frac * D[:3, 3])
        X[t] = X[t - 1] @ D
    return dataclasses.replace(s, X_j=X)


def test_a_silent_odometry_drift_is_followed_and_a_constant_estimate_error_is_not():
    # dev cad seed 2002 (e02 r0<->r1): r1's odometry reported 0.002-0.035 m per step while it moved 0.36 m,
    # unflagged; the graph, trusting odometry, lagged ever further behind accepted estimates (1.78 m off)
    noise_rot, noise_trans = 0.01, 0.02
    s = simulate_pair(seed=4, n_steps=40, speed_m=0.3, odo_rot=0.0005, odo_trans=0.001, direct_every=2,
                      direct_rot=noise_rot, direct_trans=noise_trans)
    kw = dict(direct_rot_rad=noise_rot, direct_trans_m=noise_trans, direct_trans_rel=0.0, direct_along_factor=1.0,
              direct_depth_rel_unknown=0.0)

    def trans_err(stream, out, steps):
        return [float(np.linalg.norm(out[t].T_cj_ci[:3, 3] - stream.truth[t][:3, 3])) for t in steps]

    drift = _under_reported(s, 10, 22)
    g, out = feed(drift, GraphModel(**kw, drift_after=0))
    assert g.n_drifts == 0 and max(trans_err(drift, out, range(14, 22, 2))) > 0.4  # lags behind the estimates
    g, out = feed(drift, GraphModel(**kw))
    assert g.n_drifts >= 1 and max(trans_err(drift, out, range(14, 22, 2))) < 0.1  # follows them
    assert max(trans_err(drift, out, range(22, 40))) < 0.1
    # five estimates sharing one constant error (0.5 m in the offset; indoor seed 1 had 0.22-0.24 m) against a
    # correct graph (slower robots: a tight walk): the first two are off the same way, far past the gate, but
    # the second is nearer (the graph moves toward them), so nothing fires and nothing changes
    s = simulate_pair(seed=4, n_steps=40, speed_m=0.1, odo_rot=0.0005, odo_trans=0.001, direct_every=2,
                      direct_rot=noise_rot, direct_trans=noise_trans)

    def shifted(t):
        O = s.X_j[t] @ s.truth[t] @ np.linalg.inv(s.X_i[t])
        return np.linalg.inv(s.X_j[t]) @ make_se3(np.eye(3), np.array([0.5, 0.0, 0.0])) @ O @ s.X_i[t]

    replace = {t: DirectEstimate(t, shifted(t)) for t in range(12, 22, 2)}
    g, out = feed(s, GraphModel(**kw), replace=replace)
    _, off = feed(s, GraphModel(**kw, drift_after=0), replace=replace)
    assert g.n_drifts == 0
    assert all(np.array_equal(a.T_cj_ci, b.T_cj_ci) for a, b in zip(out, off) if a.T_cj_ci is not None)


def test_an_odometry_jump_opens_the_walk_and_the_next_direct_estimate_re_anchors():
    # dev indoor seed 2001 (e01): robot r2's odometry turned 1.7 rad in one step that it never made; the
    # graph carried the offset of before the jump through eight good direct estimates after it
    s = simulate_pair(seed=6, n_steps=40, odo_rot=0.0005, odo_trans=0.001, direct_steps=[2, 4, 6, 8, 10, 24, 26, 28],
                      direct_rot=0.01, direct_trans=0.02)
    J = make_se3(so3_exp(np.array([0.0, 1.7, 0.0])), np.array([0.3, 0.0, 0.2]))
    s.X_j[15:] = s.X_j[15:] @ J  # the other robot's odometry from step 15 on (the truth and the estimates stay)
    base = dict(direct_rot_rad=0.01, direct_trans_m=0.02, direct_trans_rel=0.0, direct_along_factor=1.0,
                direct_depth_rel_unknown=0.0)
    _, out = feed(s, GraphModel(**base, odo_jump_rad=0.0, consensus_min_support=0))
    assert float(e_rot(out[24].T_cj_ci, s.truth[24])) > 1.0  # the chain holds the offset of before the jump
    _, out = feed(s, GraphModel(**base))
    assert pose_cov_sigmas(out[20].cov)[1] > 1.0  # after the jump: the predicted rotation sigma says so
    for t in range(24, 40):  # the first direct estimate after it re-anchors the graph
        assert float(e_rot(out[t].T_cj_ci, s.truth[t])) < 3 * 0.01, t


def test_a_propagated_estimate_whose_rotation_sigma_says_anywhere_is_not_reported():
    # dev indoor seed 2001 (e01 r1->r2): after an odometry jump the graph propagated a 1.7 rad wrong pose for
    # 8 steps with a predicted rotation sigma of 3.3 rad; the switch had dropped its anchor (none)
    s = simulate_pair(seed=6, n_steps=40, odo_rot=0.0005, odo_trans=0.001, direct_steps=[2, 4, 6, 8, 10, 24, 26, 28],
                      direct_rot=0.01, direct_trans=0.02)
    s.X_j[15:] = s.X_j[15:] @ make_se3(so3_exp(np.array([0.0, 1.7, 0.0])), np.array([0.3, 0.0, 0.2]))
    base = dict(direct_rot_rad=0.01, direct_trans_m=0.02, direct_trans_rel=0.0, direct_along_factor=1.0,
                direct_depth_rel_unknown=0.0)
    _, out = feed(s, GraphModel(**base))
    withheld = [t for t, r in enumerate(out) if r.uninformative]
    assert withheld == list(range(15, 24))  # from the jump to the next direct estimate
    for t in withheld:
        assert out[t].T_cj_ci is None and pose_cov_sigmas(out[t].cov)[1] > GraphModel().max_sigma_rot_rad
    assert all(out[t].T_cj_ci is not None for t in [*range(2, 15), *range(24, 40)])
    _, out = feed(s, GraphModel(**base, max_sigma_rot_rad=0.0))  # 0: always reported
    assert all(out[t].T_cj_ci is not None and not out[t].uninformative for t in range(2, 40))
    assert float(e_rot(out[20].T_cj_ci, s.truth[20])) > 1.0  # what it withheld was wrong


@pytest.mark.parametrize("verdicts,reported", [(("unverified", "unverified"), [*range(3, 6), *range(10, 13)]),
                                                (("unverified", "rejected"), [*range(3, 6), *range(10, 13)]),
                                                (("unverified", "pending"), [*range(3, 6), *range(10, 13)]),
                                                (("unverified", "verified"), [*range(3, 6), *range(10, 40)]),
                                                (("", ""), range(3, 40))])
def test_an_unconfirmed_graph_is_propagated_as_long_as_the_switch_would(verdicts, reported):
    # dev cad seed 2002 (l3 r2->r0): two unverified half-turn-wrong estimates propagated for 33 steps
    # (the switch lets an unverified candidate go after max_unverified_steps=2)
    s = simulate_pair(seed=1, n_steps=40, odo_rot=0.001, odo_trans=0.002, direct_steps=[3, 10], direct_rot=0.01,
                      direct_trans=0.02)
    _, out = feed(s, replace={3: DirectEstimate(3, s.direct[3], verdict=verdicts[0]),
                              10: DirectEstimate(10, s.direct[10], verdict=verdicts[1])})
    assert [t for t, r in enumerate(out) if r.T_cj_ci is not None] == list(reported)
    assert all(out[t].expired == (t >= 3 and t not in reported) for t in range(40))
    assert GraphModel().max_unverified_steps == AnchorConfig().max_unverified_steps


MONO_REL = MonoDepthSim().rel_sigma  # what the mono-sim depth source reports (0.094)


# a depth sensor's direct estimates, a monocular prior's: each with noise of its kind's size
@pytest.mark.parametrize("rel,noise_rot,noise_trans", [(0.0, 0.003, 0.015), (MONO_REL, 0.006, 0.05)])
def test_covariance_shrinks_after_an_anchor_and_grows_while_propagating(rel, noise_rot, noise_trans):
    s = simulate_pair(seed=1, n_steps=30, odo_rot=0.001, odo_trans=0.002, direct_steps=[2, 12, 13],
                      direct_rot=noise_rot, direct_trans=noise_trans)
    _, out = feed(s, rel=rel)
    tr = [trace(r.cov) if r.cov is not None else np.nan for r in out]
    assert all(tr[t + 1] > tr[t] for t in range(2, 11))  # propagation: grows every step
    assert tr[12] < tr[11] and tr[13] < tr[12]  # each anchor: shrinks
    assert all(tr[t + 1] > tr[t] for t in range(13, 29))
    pos, rot = pose_cov_sigmas(out[12].cov)
    assert 0 < pos < 1 and 0 < rot < 0.1


def test_predicted_sigma_is_calibrated_when_the_noise_model_is_right():
    conf = GraphModel(odo_rot_per_step=0.002, odo_rot_per_m=0.0, odo_rot_per_rad=0.0, odo_trans_per_step=0.004,
                       odo_trans_per_m=0.0, direct_rot_rad=0.02, direct_trans_m=0.05, direct_trans_rel=0.0,
                       direct_along_factor=1.0, direct_depth_rel_unknown=0.0, kernel_k=1e6)  # no kernel
    e2, s2 = [], []
    for seed in range(12):
        s = simulate_pair(seed=seed, n_steps=40, odo_rot=0.002, odo_trans=0.004, direct_every=6,
                          direct_rot=0.02, direct_trans=0.05)
        _, out = feed(s, conf)
        for t, r in enumerate(out):
            if r.T_cj_ci is not None:
                e2.append(np.sum((r.T_cj_ci[:3, 3] - s.truth[t][:3, 3]) ** 2))
                s2.append(pose_cov_sigmas(r.cov)[0] ** 2)
    ratio = np.sqrt(np.mean(e2) / np.mean(s2))
    assert 0.7 < ratio < 1.4, ratio


def test_the_window_bounds_the_graph():
    s = simulate_pair(seed=2, n_steps=300, odo_rot=0.001, odo_trans=0.002, direct_every=1, direct_rot=0.01,
                      direct_trans=0.02)
    g, out = feed(s, GraphModel(window_nodes=10))
    assert g.n_nodes == 300 and not any(r.degradations for r in out)
    kept = g._solver.smoother.calculateEstimate().keys()
    assert len(kept) <= 12
    assert float(e_rot(out[-1].T_cj_ci, s.truth[-1])) < 0.05


# --------------------------------------------------------------------------- bad input
def _good_then(bad: DirectEstimate | None, at: int = 10, **kw):
    s = simulate_pair(seed=5, n_steps=16, odo_rot=0.001, odo_trans=0.002, direct_steps=[3, 6], direct_rot=0.01,
                      direct_trans=0.02)
    return s, feed(s, replace={at: bad}, **kw)


# --------------------------------------------------------------------------- depth kinds (issue 20, graphcov)
def test_depth_sources_report_their_scale_sigma():
    from cerpe.backbones.depth import DATASET_REL_SIGMA, DepthSourceError, build_depth_source

    assert MonoDepthSim().rel_sigma == pytest.approx(np.hypot(0.08, 0.05))  # per-frame scale and distortion
    assert MonoDepthSim(scale_sigma=0.2, distortion_sigma=0.0).rel_sigma == pytest.approx(0.2)
    assert SensorDepthSim().rel_sigma == 0.0  # per-pixel noise only: it averages out over a placement
    assert build_depth_source("dataset").rel_sigma == DATASET_REL_SIGMA
    assert build_depth_source("dataset", {"rel_sigma": 0.03}).rel_sigma == 0.03
    assert getattr(build_depth_source("none"), "rel_sigma", None) is None
    with pytest.raises(DepthSourceError, match="rel_sigma"):
        build_depth_source("dataset", {"rel_sigma": -1})


def test_direct_covariance_carries_the_depth_kind():
    conf = GraphModel(direct_rot_rad=0.002, direct_trans_m=0.01, direct_trans_rel=0.005, direct_along_factor=1.5,
                       direct_depth_rot=0.05, direct_depth_across=0.3, direct_depth_along=1.0,
                       direct_depth_along_unknown=1.0, direct_depth_rel_unknown=0.5)
    rng = np.random.default_rng(0)
    T = random_se3(rng, 1.0)
    T[:3, 3] = 8.0 * T[:3, 3] / np.linalg.norm(T[:3, 3])  # the other camera 8 m away
    w = T[:3, :3].T @ T[:3, 3] / 8.0  # the line between the cameras, in camera i
    for rel, want in ((0.0, 0.0), (0.1, 0.1), (None, 0.5), (float("nan"), 0.5)):
        C = graph_mod.direct_cov(conf, DirectEstimate(0, T, depth_rel_sigma=rel))
        across = 0.01 + 8.0 * np.hypot(0.005, 0.3 * want)
        along = np.hypot(1.5 * (0.01 + 8.0 * 0.005), 1.0 * want * 8.0)
        np.testing.assert_allclose(np.diag(C[:3, :3]), np.hypot(0.002, 0.05 * want) ** 2)
        assert w @ C[3:, 3:] @ w == pytest.approx(along**2)
        u = np.cross(w, [0.0, 0.0, 1.0])
        u /= np.linalg.norm(u)
        assert u @ C[3:, 3:] @ u == pytest.approx(across**2)
        assert graph_mod.usable_cov(C)
    # a monocular prior's estimate is looser than a sensor's, by its depth's scale sigma
    mono = graph_mod.direct_cov(GraphModel(), DirectEstimate(0, T, depth_rel_sigma=MONO_REL))
    sensor = graph_mod.direct_cov(GraphModel(), DirectEstimate(0, T, depth_rel_sigma=0.0))
    assert np.sqrt(w @ mono[3:, 3:] @ w) > np.sqrt(w @ sensor[3:, 3:] @ w)
    assert np.sqrt(mono[0, 0]) > 1.1 * np.sqrt(sensor[0, 0])
    # with no depth gains the model is the one before depth kinds (isotropic across, a factor along)
    old = GraphModel(direct_depth_rot=0.0, direct_depth_across=0.0, direct_depth_along=0.0, direct_along_factor=2.0)
    C = graph_mod.direct_cov(old, DirectEstimate(0, T, depth_rel_sigma=MONO_REL))
    assert w @ C[3:, 3:] @ w == pytest.approx((2.0 * (old.direct_trans_m + 8.0 * old.direct_trans_rel)) ** 2)


def test_along_gain_per_depth_kind():
    # known answers: the along-line sigma of an estimate 10 m away per depth kind, with the floors
    # along_factor (trans_m + trans_rel d) = 2 (0 + 0.01 * 10) = 0.2 m; a reported rel uses direct_depth_along
    # (sensor 0, dataset 0.01, monocular prior 0.1), none uses direct_depth_along_unknown on rel_unknown
    conf = GraphModel(direct_rot_rad=0.002, direct_trans_m=0.0, direct_trans_rel=0.01, direct_along_factor=2.0,
                       direct_depth_rot=0.05, direct_depth_across=0.0, direct_depth_along=0.5,
                       direct_depth_along_unknown=4.0, direct_depth_rel_unknown=0.3)
    T = np.eye(4)
    T[:3, 3] = [0.0, 0.0, 10.0]
    w = np.array([0.0, 0.0, 1.0])
    for rel, gain, along in ((0.0, 0.5, 0.2), (0.01, 0.5, np.hypot(0.2, 0.05)), (0.1, 0.5, np.hypot(0.2, 0.5)),
                             (None, 4.0, np.hypot(0.2, 12.0)), (float("nan"), 4.0, np.hypot(0.2, 12.0)),
                             (-1.0, 4.0, np.hypot(0.2, 12.0))):
        assert graph_mod.along_gain(conf, rel) == gain
        C = graph_mod.direct_cov(conf, DirectEstimate(0, T, depth_rel_sigma=rel))
        assert np.sqrt(w @ C[3:, 3:] @ w) == pytest.approx(along)
        assert np.sqrt(C[3, 3]) == pytest.approx(0.1)  # across: the floor only (no across gain)
    # the unknown kind's along gain leaves its rotation and across sigmas alone (rel_unknown sets those)
    a, b = (graph_mod.direct_cov(dataclasses.replace(conf, direct_depth_along_unknown=g), DirectEstimate(0, T))
            for g in (0.0, 4.0))
    np.testing.assert_allclose(a[:5, :5], b[:5, :5])
    assert np.sqrt(a[0, 0]) == pytest.approx(np.hypot(0.002, 0.05 * 0.3))
    # the mono gain does not move the unknown kind, and vice versa
    c = graph_mod.direct_cov(dataclasses.replace(conf, direct_depth_along=9.0), DirectEstimate(0, T))
    np.testing.assert_allclose(c, b)
    with pytest.raises(GraphError, match="direct_depth_along_unknown"):
        GraphModel(direct_depth_along_unknown=-0.1)


def test_odometry_on_sensor_depth_is_tighter_but_fails_alike():
    # known answer: on a sensor-like depth source (rel <= sensor_max_rel) the noise part of an increment's
    # covariance is odo_sensor_scale^2 times the monocular prior's; the failure terms (lost steps, a jump)
    # are the same; an unknown source (None) and a monocular prior get the plain model
    conf = GraphModel(odo_sensor_scale=0.4, sensor_max_rel=0.05)
    D = make_se3(so3_exp(np.array([0.0, 0.2, 0.0])), np.array([0.5, 0.0, 0.1]))
    plain = odometry_cov(conf, D, 2)
    for rel in (0.0, 0.01):
        np.testing.assert_allclose(odometry_cov(conf, D, 2, depth_rel_sigma=rel), 0.16 * plain, rtol=1e-12)
        lost = (odometry_cov(conf, D, 2, lost_steps=1, depth_rel_sigma=rel)
                - odometry_cov(conf, D, 2, depth_rel_sigma=rel))
        np.testing.assert_allclose(lost, odometry_cov(conf, D, 2, lost_steps=1) - plain, atol=1e-15)
    for rel in (MONO_REL, None):
        np.testing.assert_array_equal(odometry_cov(conf, D, 2, depth_rel_sigma=rel), plain)
    jump = make_se3(so3_exp(np.array([0.0, 2.5, 0.0])), np.zeros(3))  # 2.5 rad in one step: a failure
    assert odometry_cov(conf, jump, 1, depth_rel_sigma=0.0)[0, 0] > 2.5**2


def test_a_pair_graph_on_sensor_depth_walks_tighter():
    s = simulate_pair(5, n_steps=20, direct_every=10)
    sigmas = []
    for rel in (None, 0.0):
        g = PairGraph(GraphModel(), depth_rel_sigma=rel)
        out = [g.step(t, s.X_i[t], s.X_j[t], t, DirectEstimate(t, s.direct[t], depth_rel_sigma=0.0)
                      if t in s.direct else None) for t in range(len(s.truth))]
        sigmas.append(np.trace(out[9].cov) - np.trace(out[0].cov))  # growth over 9 steps of propagation
    assert 0 < sigmas[1] < 0.5 * sigmas[0]


def test_inliers_weigh_estimates_on_sensor_depth_only():
    # known answers: ref 100, clip 3; on a depth sensor (rel 0) 25 inliers double every sigma, 400 halve
    # them, 10 000 stop at a third; on a monocular prior (rel above sensor_max_rel) and on no
    # metric depth (rel unknown) the inliers change nothing, nor do unknown inliers (-1)
    conf = GraphModel(direct_inliers_ref=100.0, direct_inliers_clip=3.0, sensor_max_rel=0.05)
    T = random_se3(np.random.default_rng(3), 2.0)
    for rel in (0.0, 0.01):
        base = graph_mod.direct_cov(conf, DirectEstimate(0, T, inliers=100, depth_rel_sigma=rel))
        assert np.array_equal(base, graph_mod.direct_cov(conf, DirectEstimate(0, T, depth_rel_sigma=rel)))
        for n, f in ((25, 2.0), (400, 0.5), (10_000, 1.0 / 3.0)):
            C = graph_mod.direct_cov(conf, DirectEstimate(0, T, inliers=n, depth_rel_sigma=rel))
            np.testing.assert_allclose(C, f**2 * base, rtol=1e-12)
    for rel in (MONO_REL, None):
        base = graph_mod.direct_cov(conf, DirectEstimate(0, T, inliers=100, depth_rel_sigma=rel))
        for n in (25, 400):
            C = graph_mod.direct_cov(conf, DirectEstimate(0, T, inliers=n, depth_rel_sigma=rel))
            assert np.array_equal(C, base)
    off = dataclasses.replace(conf, direct_inliers_ref=0.0)
    assert np.array_equal(graph_mod.direct_cov(off, DirectEstimate(0, T, inliers=25, depth_rel_sigma=0.0)),
                          graph_mod.direct_cov(off, DirectEstimate(0, T, inliers=400, depth_rel_sigma=0.0)))


# the noise model of cerpe-graph before depth kinds (commit a50f8ce's calibration, one model for every depth)
ONE_MODEL = {"direct_rot_rad": 0.004, "direct_trans_m": 0.001, "direct_trans_rel": 0.0275, "direct_along_factor": 2.0,
             "direct_depth_rot": 0.0, "direct_depth_across": 0.0, "direct_depth_along": 0.0}


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_a_consistent_mono_distance_bias_is_pulled_toward_the_truth(seed):
    # every direct estimate of a monocular prior 10 % short along the line between the cameras while the
    # robots drive apart (the line turns): with the depth kind's covariance (loose along the line, tight
    # across it) the lines' cross-track parts pin the other robot down; one model trusts the biased range
    s = simulate_pair(seed=seed, n_steps=60, speed_m=0.3, odo_rot=0.0005, odo_trans=0.002, direct_every=2,
                      direct_rot=0.005, direct_trans=0.01)
    short = {t: make_se3(T[:3, :3], 0.9 * T[:3, 3]) for t, T in s.direct.items()}
    err = {}
    # both at the rotation floor and kernel this was calibrated with (a 4th-digit margin: the issue-20
    # recalibration, 0.006 rad and k 2, moves both by more than it); this checks the depth kinds, not those
    old = {"direct_rot_rad": 0.004, "kernel_k": 3.0}
    for name, conf in (("kind", GraphModel(**old)), ("one-model", GraphModel(**{**ONE_MODEL, **old}))):
        _, out = feed(s, conf, replace={t: DirectEstimate(t, T, depth_rel_sigma=MONO_REL) for t, T in short.items()})
        err[name] = [np.linalg.norm(r.T_cj_ci[:3, 3] - s.truth[t][:3, 3]) for t, r in enumerate(out)]
    bias = [0.1 * np.linalg.norm(s.truth[t][:3, 3]) for t in range(len(s.truth))]
    assert err["kind"][-1] < err["one-model"][-1] < bias[-1]  # both below the raw bias, the kind's closer
    assert np.mean(err["kind"][20:]) < np.mean(err["one-model"][20:])  # and on average once apart


@pytest.mark.parametrize("cov", [np.zeros((6, 6)), np.full((6, 6), np.nan), -np.eye(6), np.eye(5)])
def test_degenerate_covariance_is_counted_and_the_estimate_kept(cov):
    s, (g, out) = _good_then(None)
    T = s.truth[10]
    s2, (g2, out2) = _good_then(DirectEstimate(10, T, cov=cov))
    assert out2[10].degradations == ["graph:degenerate-covariance"] and not out2[10].measured
    np.testing.assert_allclose(out2[10].T_cj_ci, out[10].T_cj_ci)  # as if it had not come
    np.testing.assert_allclose(out2[10].cov, out[10].cov)
    assert known("graph:degenerate-covariance")


def test_anchor_between_poses_the_graph_does_not_have_is_out_of_order():
    s = simulate_pair(seed=6, n_steps=16, direct_steps=[3, 9])
    # the other robot's pose of step 9 never arrived: its estimate relates poses the graph lacks
    _, out = feed(s, skip_pose_j={9})
    assert out[9].degradations == ["graph:out-of-order"] and out[9].node_step == 3
    assert out[9].T_cj_ci is not None  # the last good estimate, propagated with the stale pose
    # an estimate of an older step than the graph's newest node (messages out of order)
    g, _ = feed(s)
    late = g.step(16, s.X_i[15], s.X_j[15], 15, DirectEstimate(5, s.truth[5]))
    assert late.degradations == ["graph:out-of-order"] and late.node_step == 9
    # before any pose of the other robot: counted, nothing to report
    first = PairGraph().step(0, np.eye(4), None, -1, DirectEstimate(0, np.eye(4)))
    assert first.degradations == ["graph:out-of-order"] and first.T_cj_ci is None


def test_solver_exception_keeps_the_last_good_estimate(monkeypatch):
    s = simulate_pair(seed=7, n_steps=16, odo_rot=0.001, odo_trans=0.002, direct_steps=[3, 6, 10, 13],
                      direct_rot=0.01, direct_trans=0.02)
    _, ref = feed(s, replace={10: None})
    g = PairGraph()
    out = []
    real_add = graph_mod._Solver.add
    for t in range(16):
        if t == 10:
            monkeypatch.setattr(graph_mod._Solver, "add", lambda *a, **k: (_ for _ in ()).throw(RuntimeError("boom")))
        if t == 11:
            monkeypatch.setattr(graph_mod._Solver, "add", real_add)
        d = DirectEstimate(t, s.direct[t]) if t in s.direct else None
        out.append(g.step(t, s.X_i[t], s.X_j[t], t, d))
    assert out[10].degradations == ["graph:solver-failed"] and out[10].node_step == 6
    np.testing.assert_allclose(out[10].T_cj_ci, ref[10].T_cj_ci, atol=1e-9)
    # the graph goes on from the last good node: the next estimate is taken in
    assert out[13].measured and not out[13].degradations
    assert float(e_rot(out[15].T_cj_ci, s.truth[15])) < 0.05


def test_graph_that_does_not_converge_keeps_the_last_good_estimate():
    s = simulate_pair(seed=8, n_steps=16, odo_rot=0.001, odo_trans=0.002, direct_steps=[3, 8], direct_rot=0.05,
                      direct_trans=0.1)
    conf = GraphModel(max_iterations=1, converge_tol=1e-300)
    _, out = feed(s, conf)
    assert out[3].measured  # a single prior converges at once
    assert out[8].degradations == ["graph:not-converged"] and out[8].node_step == 3
    np.testing.assert_allclose(out[8].T_cj_ci, feed(s, replace={8: None})[1][8].T_cj_ci, atol=1e-9)


def test_graph_degradations_are_listed():
    for name in graph_mod.GRAPH_DEGRADATIONS:
        assert name in DEGRADATIONS


# --------------------------------------------------------------------------- in the agent
def _run(world, config):
    team = Team(world.robot_ids, OverlapDescriptor(world), GTBackbone(world, seed=1, trans_noise=0.02,
                                                                      rot_noise_rad=0.005),
                SensorDepthDouble(), config)
    return list(team.run_encounter(world.to_encounter()))


def test_agent_graph_backend_same_messages_and_pass_estimates_with_covariance():
    world = make_world(3, 30, seed=2)
    base = AlgorithmConfig().override({"scale.min_pixels": 20})
    switch = _run(world, base)
    graph = _run(world, base.override({"backend.kind": "graph"}))
    err: dict[str, list[float]] = {"graph": [], "switch": []}
    for a, b in zip(switch, graph):
        for ra, rb in zip(a.robots, b.robots):  # the same messages, bytes and odometry
            assert ra.bytes_sent == rb.bytes_sent and ra.degradations == rb.degradations
            np.testing.assert_array_equal(ra.T_odom_cam, rb.T_odom_cam)
            assert rb.timings_s["graph"] > 0 and ra.timings_s.get("graph", 0.0) == 0.0
        for pa, pb in zip(a.pairs, b.pairs):
            assert (pa.gate_open, pa.gate_score, pa.bytes_pair, pa.anchor_verdict, pa.direct_via) == \
                (pb.gate_open, pb.gate_score, pb.bytes_pair, pb.anchor_verdict, pb.direct_via)
            if pa.T_direct is None:
                assert pb.T_direct is None
            else:
                np.testing.assert_array_equal(pa.T_direct, pb.T_direct)
            assert pa.cov is None and np.isnan(pa.as_row()["sigma_pos_m"])  # the paper's CERPE: no covariance
            assert (pb.source == "none") == (pb.T_cj_ci is None) == (pb.cov is None)
            if pb.source == "none":
                assert pa.source == "none"  # nothing before the first direct estimate, as CERPE
            else:
                row = pb.as_row()
                assert row["sigma_pos_m"] > 0 and row["sigma_rot_rad"] > 0
                i, j = world.index(pb.ego), world.index(pb.other)
                gt = world.gt_T_cj_ci(a.step, i, j)
                err["graph"].append(float(e_rot(pb.T_cj_ci, gt)))
            if pa.T_cj_ci is not None:
                err["switch"].append(float(e_rot(pa.T_cj_ci, world.gt_T_cj_ci(a.step, world.index(pa.ego),
                                                                             world.index(pa.other)))))
    assert max(err["graph"]) < 0.2 and np.mean(err["graph"]) < 0.1 and len(err["graph"]) >= len(err["switch"])
    # the graph estimates every step the switch estimates (success >= CERPE's)
    assert sum(p.source != "none" for r in graph for p in r.pairs) >= sum(p.source != "none" for r in switch
                                                                         for p in r.pairs)


def test_paper_cerpe_ignores_the_graph_configuration():
    world = make_world(2, 20, seed=3)
    base = AlgorithmConfig().override({"scale.min_pixels": 20})
    a = _run(world, base)
    b = _run(world, base.override({"backend.graph.window_nodes": 2, "backend.graph.kernel_k": 0.1}))
    for ra, rb in zip(a, b):
        for pa, pb in zip(ra.pairs, rb.pairs):
            assert pa.as_row().keys() == pb.as_row().keys()
            assert {k: v for k, v in pa.as_row().items() if v == v} == {k: v for k, v in pb.as_row().items() if v == v}


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_defaults_let_scattered_estimates_pull_the_graph_off_a_bad_first_one(seed):
    # indoor-s1's pair (development data): a first direct estimate 0.7 m / 0.15 rad off, then estimates whose rotations
    # scatter as the dev runs' do (0.012 rad per axis); at the previous direct_rot_rad 0.004 and kernel_k 3
    # each of them is a 10-30 sigma outlier to every other and the Cauchy kernel keeps the first one longer
    s = simulate_pair(seed=seed, n_steps=14, speed_m=0.05, odo_rot=0.0005, odo_trans=0.002,
                      direct_steps=[2, 3, 5, 6, 8, 9, 11], direct_rot=0.012, direct_trans=0.05)
    bad = s.truth[2] @ make_se3(so3_exp(np.array([0.0, 0.15, 0.0])), np.array([0.5, 0.0, 0.5]))
    err = {}
    for name, conf in (("new", GraphModel()), ("old", GraphModel(direct_rot_rad=0.004, kernel_k=3.0, max_iterations=30))):
        _, out = feed(s, conf, replace={2: DirectEstimate(2, bad)})
        err[name] = np.array([np.linalg.norm(out[t].T_cj_ci[:3, 3] - s.truth[t][:3, 3]) for t in range(3, 14)])
    assert np.all(err["new"] < err["old"])
    assert err["new"][-1] < 0.95 * err["old"][-1]

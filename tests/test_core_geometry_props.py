"""Randomised SE(3)/Sim(3)/quaternion identities, propagation exactness, e_rot vs roma."""
from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from cerpe.geometry import (
    compose, e_rot, e_rot_quat, make_sim3, make_se3, matrix_to_quat_wxyz, matrix_to_quat_xyzw, paper_T_ij,
    propagate_relative_pose, quat_wxyz_to_matrix, quat_xyzw_to_matrix, random_se3, se3_from_tq_xyzw,
    se3_inverse, se3_to_tq_xyzw, sim3_inverse, so3_exp, wxyz_to_xyzw, xyzw_to_wxyz,
)

finite = st.floats(-1.0, 1.0, allow_nan=False, allow_infinity=False)
quats = st.tuples(finite, finite, finite, finite).map(np.array).filter(lambda q: np.linalg.norm(q) > 0.1)
trans = st.tuples(*[st.floats(-100, 100, allow_nan=False)] * 3).map(np.array)
poses = st.builds(se3_from_tq_xyzw, trans, quats)
seeds = st.integers(0, 2**31 - 1)
FAST = settings(max_examples=60, deadline=None)


def _same_rotation_quat(q1: np.ndarray, q2: np.ndarray) -> bool:
    return np.allclose(q1, q2, atol=1e-9) or np.allclose(q1, -q2, atol=1e-9)


@FAST
@given(poses)
def test_inverse_round_trip(T):
    np.testing.assert_allclose(T @ se3_inverse(T), np.eye(4), atol=1e-9)
    np.testing.assert_allclose(se3_inverse(se3_inverse(T)), T, atol=1e-9)


@FAST
@given(poses, poses, poses)
def test_compose_inverse_reverses_order(A, B, C):
    np.testing.assert_allclose(se3_inverse(compose(A, B, C)),
                               compose(se3_inverse(C), se3_inverse(B), se3_inverse(A)), atol=1e-8)


@FAST
@given(quats)
def test_quaternion_layouts_both_ways(q_raw):
    q_xyzw = q_raw / np.linalg.norm(q_raw)
    R = quat_xyzw_to_matrix(q_xyzw)
    assert _same_rotation_quat(matrix_to_quat_xyzw(R), q_xyzw)
    q_wxyz = xyzw_to_wxyz(q_xyzw)
    np.testing.assert_allclose(q_wxyz[0], q_xyzw[3])
    np.testing.assert_allclose(quat_wxyz_to_matrix(q_wxyz), R, atol=1e-12)
    assert _same_rotation_quat(matrix_to_quat_wxyz(R), q_wxyz)
    np.testing.assert_allclose(wxyz_to_xyzw(xyzw_to_wxyz(q_xyzw)), q_xyzw)
    np.testing.assert_allclose(R @ R.T, np.eye(3), atol=1e-12)
    assert np.linalg.det(R) == pytest.approx(1.0)


@FAST
@given(poses)
def test_tq_round_trip(T):
    t, q = se3_to_tq_xyzw(T)
    assert q[3] >= 0
    np.testing.assert_allclose(se3_from_tq_xyzw(t, q), T, atol=1e-9)


@FAST
@given(quats, trans, st.floats(0.01, 100.0))
def test_sim3_inverse(q, t, s):
    S = make_sim3(s, quat_xyzw_to_matrix(q), t)
    np.testing.assert_allclose(S @ sim3_inverse(S), np.eye(4), atol=1e-7 * max(1.0, s, 1 / s))
    np.testing.assert_allclose(sim3_inverse(sim3_inverse(S)), S, atol=1e-7 * max(1.0, s, 1 / s) * 100)


@settings(max_examples=20, deadline=None)
@given(seeds)
def test_propagation_with_exact_ego_motion_is_exact_for_100_steps(seed):
    """One anchor at step 0, then 100 steps of random motion of both robots, each
    robot's odometry in its own unrelated frame: the propagated T_cj_ci equals the
    truth to 1e-9."""
    rng = np.random.default_rng(seed)
    n = 100
    T_w_ci = [random_se3(rng, 20.0)]
    T_w_cj = [random_se3(rng, 20.0)]
    for _ in range(n):
        T_w_ci.append(T_w_ci[-1] @ make_se3(so3_exp(rng.normal(0, 0.1, 3)), rng.normal(0, 1.0, 3)))
        T_w_cj.append(T_w_cj[-1] @ make_se3(so3_exp(rng.normal(0, 0.1, 3)), rng.normal(0, 1.0, 3)))
    odom_i = random_se3(rng, 50.0)  # T_odom_world of each robot: arbitrary, different
    odom_j = random_se3(rng, 50.0)
    X_i = [odom_i @ T for T in T_w_ci]
    X_j = [odom_j @ T for T in T_w_cj]
    anchor = paper_T_ij(T_w_ci[0], T_w_cj[0])
    for t in range(1, n + 1):
        est = propagate_relative_pose(anchor, X_i[0], X_i[t], X_j[0], X_j[t])
        np.testing.assert_allclose(est, paper_T_ij(T_w_ci[t], T_w_cj[t]), atol=1e-9)


def test_e_rot_matches_roma_geodesic_distance():
    roma = pytest.importorskip("roma")
    torch = pytest.importorskip("torch")
    rng = np.random.default_rng(7)
    A = np.stack([random_se3(rng) for _ in range(200)])
    # include near-identical and near-opposite pairs, where arcsin/arccos formulas differ most
    B = np.stack([a @ make_se3(so3_exp(rng.normal(0, 1, 3) * s), np.zeros(3))
                  for a, s in zip(A, np.r_[np.full(50, 1e-4), np.full(100, 1.0), np.full(50, 3.0)])])
    ours = e_rot(A, B)
    ref = roma.rotmat_geodesic_distance(torch.from_numpy(A[:, :3, :3]), torch.from_numpy(B[:, :3, :3])).numpy()
    np.testing.assert_allclose(ours, ref, atol=1e-6)
    qa, qb = matrix_to_quat_xyzw(A[:, :3, :3]), matrix_to_quat_xyzw(B[:, :3, :3])
    ref_q = roma.unitquat_geodesic_distance(torch.from_numpy(qa), torch.from_numpy(qb)).numpy()
    np.testing.assert_allclose(e_rot_quat(qa, qb), ref_q, atol=1e-9)
    np.testing.assert_allclose(e_rot_quat(qa, -qb), ref_q, atol=1e-9)  # sign-invariant

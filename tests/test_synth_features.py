"""Real feature detectors work on the rendered worlds (640x480): SIFT keypoint counts and
two-view relative rotation from SIFT + essential matrix RANSAC."""
from __future__ import annotations

import cv2
import numpy as np
import pytest

from cerpe.geometry import paper_T_ij, rotation_angle
from cerpe.synth.renderer import render
from cerpe.synth.worlds import plan_encounter

CONF = {"n_frames": 20, "fps": 10.0, "size": (640, 480), "n_robots": 2}


def _pair_1m_apart(plan, k=0, t0=0, dist_m=1.0):
    P = plan.T_world_cam[k][:, :3, 3]
    d = np.linalg.norm(P - P[t0], axis=1)
    d[: t0 + 1] = np.inf
    t1 = int(np.argmin(np.abs(d - dist_m)))
    return t0, t1, float(d[t1])


def _gray(plan, k, t):
    return cv2.cvtColor(render(plan.faces_at(t, k), plan.T_world_cam[k, t], plan.intrinsics, plan.ctx).rgb,
                        cv2.COLOR_RGB2GRAY)


def _moving_fraction(plan, k, t):
    """Share of the image covered by moving objects (other vehicles, the truck): their
    points break the static two-view geometry, so the rotation check avoids such frames."""
    small = plan.intrinsics.scaled(0.25)
    fid = render(plan.faces_at(t, k), plan.T_world_cam[k, t], small, plan.ctx, with_rgb=False).face_id
    return float((fid >= len(plan.static)).mean())


def _static_pair(plan, k=0):
    for t0 in range(plan.n_steps):
        t0_, t1, dist = _pair_1m_apart(plan, k, t0)
        if 0.7 < dist < 1.5 and _moving_fraction(plan, k, t0_) < 0.1 and _moving_fraction(plan, k, t1) < 0.1:
            return t0_, t1, dist
    pytest.fail("no pair of frames 1 m apart without large moving objects")


@pytest.mark.slow
@pytest.mark.parametrize("index", [0, 1, 2, 3])
def test_sift_essential_matrix_recovers_rotation_within_1_degree(index):
    plan = plan_encounter("cad-intersection", 0, index, CONF)
    t0, t1, dist = _static_pair(plan)
    sift = cv2.SIFT_create()
    g0, g1 = _gray(plan, 0, t0), _gray(plan, 0, t1)
    k0, d0 = sift.detectAndCompute(g0, None)
    k1, d1 = sift.detectAndCompute(g1, None)
    assert len(k0) >= 500 and len(k1) >= 500, (len(k0), len(k1))
    good = [a for a, b in cv2.BFMatcher().knnMatch(d0, d1, k=2) if a.distance < 0.8 * b.distance]
    p0 = np.float64([k0[m.queryIdx].pt for m in good])
    p1 = np.float64([k1[m.trainIdx].pt for m in good])
    K = plan.intrinsics.K
    E, mask = cv2.findEssentialMat(p0, p1, K, cv2.RANSAC, 0.999, 1.0)
    _, R, _, mask = cv2.recoverPose(E, p0, p1, K, mask=mask)
    assert mask.sum() >= 50
    T_gt = paper_T_ij(plan.T_world_cam[0, t0], plan.T_world_cam[0, t1])  # camera t0 -> camera t1
    err_deg = np.rad2deg(float(rotation_angle(R.T @ T_gt[:3, :3])))
    assert err_deg < 1.0, (t0, t1, err_deg)


@pytest.mark.slow
def test_indoor_frame_has_enough_sift_keypoints():
    plan = plan_encounter("indoor-team", 0, 0, {**CONF, "n_robots": 3})
    kp = cv2.SIFT_create().detect(_gray(plan, 1, 5), None)
    assert len(kp) >= 500, len(kp)

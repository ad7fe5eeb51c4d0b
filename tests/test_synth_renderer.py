"""Renderer: exact depth on known geometry, culling, rigid-motion invariance, bad input."""
from __future__ import annotations

import numpy as np
import pytest

from cerpe.geometry import random_se3
from cerpe.scene import CameraIntrinsics
from cerpe.synth import SynthError
from cerpe.synth import textures as tx
from cerpe.synth.plan import camera_pose
from cerpe.synth.renderer import FaceSet, Material, box, quad, render

K = CameraIntrinsics(100.0, 100.0, 39.5, 29.5, 80, 60)
GREY = Material(tx.PLAIN, (0.5, 0.5, 0.5), seed=1)


def test_fronto_parallel_wall_has_exact_depth():
    # wall at z = 5 in the camera frame (camera at origin looking along +z), facing the camera
    wall = quad((-1, -0.75, 5.0), (0, 1.5, 0), (2, 0, 0), GREY)  # normal = y x x = -z
    out = render(wall, np.eye(4), K, tx.ShadeContext(outdoor=False))
    u = (np.arange(80) - K.cx) / K.fx * 5.0
    v = (np.arange(60) - K.cy) / K.fy * 5.0
    inside = (np.abs(u)[None, :] < 1) & (np.abs(v)[:, None] < 0.75)
    assert inside.sum() > 100 and (~inside).sum() > 100
    np.testing.assert_allclose(out.depth_m[inside], 5.0, rtol=1e-5)
    assert np.all(out.depth_m[~inside] == 0)
    assert out.rgb.shape == (60, 80, 3) and out.rgb.dtype == np.uint8


def test_ground_plane_depth_matches_closed_form():
    h = 1.5
    ground = quad((-100, -100, 0), (200, 0, 0), (0, 200, 0), GREY)
    T = camera_pose(0.0, 0.0, h, 0.0, 0.0)  # level camera, looking along world x
    d = render(ground, T, K, tx.ShadeContext(outdoor=True)).depth_m
    rows = np.arange(60)
    below = rows > K.cy + 0.5
    expected = h * K.fy / (rows[below] - K.cy)
    ok = expected < 90  # inside the 100 m ground patch
    np.testing.assert_allclose(d[below][ok][:, 40], expected[ok], rtol=1e-5)
    assert np.all(d[rows < K.cy] == 0)  # above the horizon: sky, no surface


def test_camera_inside_closed_box_sees_through_it():
    b = box((0.0, 0.0), -1.0, (2.0, 2.0, 2.0), 0.3, GREY, bottom=True)
    out = render(b, camera_pose(0.0, 0.0, 0.0, 0.7), K)
    assert np.all(out.depth_m == 0) and np.all(out.face_id == -1)


def test_nearer_face_occludes():
    far = quad((-5, -5, 10.0), (0, 10, 0), (10, 0, 0), GREY)
    near = quad((-0.5, -0.5, 3.0), (0, 1, 0), (1, 0, 0), GREY)
    d = render(FaceSet.concat([far, near]), np.eye(4), K).depth_m
    assert d[30, 40] == pytest.approx(3.0, rel=1e-5)
    assert d[2, 2] == pytest.approx(10.0, rel=1e-5)


@pytest.mark.parametrize("seed", range(4))
def test_depth_invariant_to_a_rigid_motion_of_world_and_camera(seed):
    rng = np.random.default_rng(seed)
    faces = FaceSet.concat([box((rng.uniform(4, 8), rng.uniform(-2, 2)), rng.uniform(-1, 0), (1, 1.5, 2),
                                rng.uniform(0, 3), GREY) for _ in range(4)]
                           + [quad((-20, -20, -1.5), (40, 0, 0), (0, 40, 0), GREY)])
    T_cam = camera_pose(0.0, 0.0, 0.0, 0.0, 0.1)
    G = random_se3(rng, 20.0)
    d0 = render(faces, T_cam, K, with_rgb=False).depth_m
    d1 = render(faces.transformed(G), G @ T_cam, K, with_rgb=False).depth_m
    assert (d0 > 0).mean() > 0.5
    np.testing.assert_allclose(d1, d0, rtol=1e-4, atol=1e-4)


def test_bad_inputs_raise_synth_error():
    with pytest.raises(SynthError, match="orthogonal"):
        quad((0, 0, 0), (1, 0, 0), (1, 1, 0), GREY)
    with pytest.raises(SynthError, match="positive"):
        box((0, 0), 0, (1, 0, 1), 0, GREY)
    bad = np.eye(4)
    bad[0, 3] = np.nan
    with pytest.raises(SynthError, match="T_world_cam"):
        render(quad((0, 0, 5), (1, 0, 0), (0, 1, 0), GREY), bad, K)


def test_textures_are_deterministic_and_textured():
    wall = quad((-2, -1.5, 2.0), (0, 3, 0), (4, 0, 0), Material(tx.FACADE, (0.7, 0.5, 0.4), (3.0, 2.5, 1.0, 1.0), seed=3))
    a = render(wall, np.eye(4), K).rgb
    b = render(wall, np.eye(4), K).rgb
    assert np.array_equal(a, b)
    assert a.astype(float).std() > 10  # not a flat colour

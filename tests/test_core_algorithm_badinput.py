"""Malformed input raises AlgorithmError naming robot/step/field; run-time faults are counted."""
from __future__ import annotations

import numpy as np
import pytest

from cerpe.knobs import KnobError
from cerpe.algorithm import AlgorithmError, AlgorithmConfig, RobotAgent, Team, direct_relative, ego_motion
from cerpe.errors import CerpeError
from cerpe.protocols import FrameContext
from gt_backbone import GTBackbone, OverlapDescriptor, SensorDepthDouble, make_world

CFG = AlgorithmConfig().override({"scale.min_pixels": 20})


@pytest.fixture(scope="module")
def world():
    return make_world(2, 8, seed=1)


def _team(world, descriptor=None, backbone=None, depth=None):
    return Team(world.robot_ids, descriptor or OverlapDescriptor(world), backbone or GTBackbone(world),
                depth or SensorDepthDouble(), CFG)


def _inputs(world, t: int):
    imgs = [world.images[a][t] for a in range(2)]
    ctx = [FrameContext(r, t, world.intrinsics, world.depth_m[a][t]) for a, r in enumerate(world.robot_ids)]
    return imgs, ctx


def test_errors_are_cerpe_and_value_errors():
    assert issubclass(AlgorithmError, CerpeError) and issubclass(AlgorithmError, ValueError)


NAN_POSE = np.eye(4)
NAN_POSE[1, 3] = np.nan
INF_POSE = np.eye(4)
INF_POSE[0, 0] = np.inf


@pytest.mark.parametrize("args, field", [
    ((NAN_POSE, np.eye(4), np.eye(4), 1.0), "X_kf"),
    ((np.eye(4), INF_POSE, np.eye(4), 1.0), "T_frame_kf"),
    ((np.eye(4), np.eye(4), np.eye(3), 1.0), "T_frame_cur"),
    ((np.eye(4), np.eye(4), np.eye(4), float("nan")), "scale"),
    ((np.eye(4), np.eye(4), np.eye(4), 0.0), "scale"),
])
def test_ego_motion_rejects_bad_poses_and_scale(args, field):
    with pytest.raises(AlgorithmError, match=field):
        ego_motion(*args)


def test_direct_relative_rejects_non_finite():
    with pytest.raises(AlgorithmError, match="T_frame_cj"):
        direct_relative(np.eye(4), NAN_POSE, 1.0)
    with pytest.raises(AlgorithmError, match="T_frame_ci"):
        direct_relative(INF_POSE, np.eye(4), 1.0)


def test_ego_motion_and_direct_known_answer():
    rng = np.random.default_rng(0)
    from cerpe.geometry import random_se3
    A, B, F, X = (random_se3(rng) for _ in range(4))
    unit = 3.0  # backbone units per metre; frame F arbitrary
    def in_frame(T):
        out = F @ T
        out[:3, 3] *= unit
        return out
    np.testing.assert_allclose(ego_motion(X, in_frame(A), in_frame(B), 1 / unit), X @ np.linalg.inv(A) @ B,
                               atol=1e-9)
    np.testing.assert_allclose(direct_relative(in_frame(A), in_frame(B), 1 / unit), np.linalg.inv(B) @ A,
                               atol=1e-9)


def test_zero_size_and_wrong_type_images(world):
    team = _team(world)
    imgs, ctx = _inputs(world, 0)
    with pytest.raises(AlgorithmError, match="robot r1 step 0: image must be a non-empty"):
        team.step([imgs[0], np.zeros((0, 32, 3), np.uint8)], ctx)
    team = _team(world)
    with pytest.raises(AlgorithmError, match="uint8"):
        team.step([imgs[0].astype(np.float32), imgs[1]], ctx)


def test_image_and_depth_shape_mismatch(world):
    team = _team(world)
    imgs, ctx = _inputs(world, 0)
    ctx[1] = FrameContext("r1", 0, world.intrinsics, np.ones((10, 10), np.float32))
    with pytest.raises(AlgorithmError, match="robot r1 step 0: sensor_depth_m shape"):
        team.step(imgs, ctx)
    team = _team(world)
    imgs, ctx = _inputs(world, 0)
    with pytest.raises(AlgorithmError, match="intrinsics are for 32x24"):
        team.step([imgs[0], np.zeros((20, 20, 3), np.uint8)], [ctx[0], FrameContext("r1", 0, world.intrinsics)])


class _BadDescriptor(OverlapDescriptor):
    def __init__(self, world, mode):
        super().__init__(world)
        self.mode = mode

    def describe(self, view):
        d = super().describe(view)
        if self.mode == "short":
            return d[:-1]
        if self.mode == "nan":
            d[0] = np.nan
        if self.mode == "2d":
            return d[None]
        return d


@pytest.mark.parametrize("mode, msg", [("short", "descriptor has shape"), ("2d", "descriptor has shape"),
                                       ("nan", "descriptor contains NaN")])
def test_bad_descriptor_from_encoder_raises(world, mode, msg):
    team = _team(world, descriptor=_BadDescriptor(world, mode))
    with pytest.raises(AlgorithmError, match=f"robot r0 step 0: {msg}"):
        team.step(*_inputs(world, 0))


def test_received_descriptor_of_wrong_length_is_counted_not_fatal(world):
    team = _team(world)
    a = team.agents[0]
    a.begin_step(*[x[0] for x in _inputs(world, 0)])
    assert np.isnan(a.score_descriptor("r1", np.ones(3)))
    assert np.isnan(a.score_descriptor("r1", np.zeros(a.cur.descriptor.size)))
    assert a.cur.degradations == ["descriptor:wrong-length", "descriptor:other-zero-norm"]
    assert not a.gate_open("r1")


class _WrongCountBackbone(GTBackbone):
    def infer(self, views):
        return super().infer(list(views)[:1] + list(views))


class _NaNPoseBackbone(GTBackbone):
    def infer(self, views):
        out = super().infer(views)
        if views[0].key == ("r0", 3):
            out.T_frame_cam[0, 0, 3] = np.nan  # claims valid, pose is NaN
        return out


def test_backbone_with_wrong_number_of_views_raises(world):
    team = _team(world, backbone=_WrongCountBackbone(world))
    with pytest.raises(AlgorithmError, match="backbone returned 2 views for 1 given"):
        team.step(*_inputs(world, 0))


class _NotAnOutputBackbone(GTBackbone):
    def infer(self, views):
        return {"T_frame_cam": super().infer(views).T_frame_cam}


class _OddTimingsBackbone(GTBackbone):
    def infer(self, views):
        out = super().infer(views)
        out.timings_s = {"solve": 0.01, "note": "fast", "nan": float("nan")}
        return out


def test_backbone_returning_something_else_raises_the_algorithm_error(world):
    team = _team(world, backbone=_NotAnOutputBackbone(world))
    with pytest.raises(AlgorithmError, match="backbone returned dict views for 1 given"):
        team.step(*_inputs(world, 0))


def test_backbone_timings_that_are_not_seconds_are_left_out(world):
    team = _team(world, backbone=_OddTimingsBackbone(world))
    rec = team.step(*_inputs(world, 0)).robots[0]
    assert rec.parts_s.get("backbone:solve") == pytest.approx(0.01)
    assert "backbone:note" not in rec.parts_s and "backbone:nan" not in rec.parts_s


def test_backbone_nan_pose_is_counted_and_robot_keeps_going(world):
    team = _team(world, backbone=_NaNPoseBackbone(world))
    results = list(team.run_encounter(world.to_encounter()))
    r0 = results[3].robots[0]
    assert "backbone:non-finite-pose" in r0.degradations and "ego:no-estimate" in r0.degradations
    np.testing.assert_array_equal(r0.T_odom_cam, results[2].robots[0].T_odom_cam)
    assert all(np.all(np.isfinite(r.robots[0].T_odom_cam)) for r in results)


class _BadDepth(SensorDepthDouble):
    def depth_m(self, view, frame):
        return np.ones((2, 3, 4), np.float32)


def test_depth_source_with_wrong_dims_raises(world):
    team = _team(world, depth=_BadDepth())
    with pytest.raises(AlgorithmError, match="depth source 'sensor-double' returned shape"):
        team.step(*_inputs(world, 0))


def test_non_finite_pose_of_other_robot_rejected(world):
    team = _team(world)
    a = team.agents[0]
    with pytest.raises(AlgorithmError, match="pose of robot r1"):
        a.note_pose("r1", 0, NAN_POSE)


def test_phase_order_and_empty_memory(world):
    a = RobotAgent("r0", 0, CFG, OverlapDescriptor(world), GTBackbone(world), SensorDepthDouble())
    with pytest.raises(AlgorithmError, match="no step in progress"):
        a.update_odometry()
    a.begin_step(world.images[0][0], FrameContext("r0", 0, world.intrinsics, world.depth_m[0][0]))
    with pytest.raises(AlgorithmError, match="before joint_pass"):
        a.update_odometry()
    with pytest.raises(AlgorithmError, match="before joint_pass"):
        a.estimate_scale()
    assert len(a.memory) == 0  # empty memory at the first step: identity pose, scale from current frame
    a.joint_pass()
    assert np.isfinite(a.estimate_scale())
    np.testing.assert_array_equal(a.update_odometry(), np.eye(4))


def test_team_level_consistency_checks(world):
    team = _team(world)
    imgs, ctx = _inputs(world, 0)
    with pytest.raises(AlgorithmError, match="1 images and 2 contexts"):
        team.step(imgs[:1], ctx)
    with pytest.raises(AlgorithmError, match="different steps"):
        team.step(imgs, [ctx[0], FrameContext("r1", 1, world.intrinsics, world.depth_m[1][1])])
    with pytest.raises(AlgorithmError, match="belongs to robot 'r1'"):
        team.step(imgs, ctx[::-1])
    team = _team(world)
    team.step(*_inputs(world, 1))
    with pytest.raises(AlgorithmError, match="steps must increase"):
        team.step(*_inputs(world, 1))
    with pytest.raises(AlgorithmError, match="unique"):
        Team(["a", "a"], OverlapDescriptor(world), GTBackbone(world), SensorDepthDouble())
    other = make_world(3, 4, seed=2).to_encounter()
    with pytest.raises(AlgorithmError, match="differ from the team"):
        list(team.run_encounter(other))


@pytest.mark.parametrize("key, value", [
    ("gate.tau", 1.2), ("memory.tau_m", float("nan")), ("messages.descriptor_dtype", "bf16"),
    ("messages.reply_quality", 101), ("scale.min_pixels", 0), ("scale.min_pixels", "abc"),
    ("messages.reply_quality", float("nan")),
])
def test_bad_config(key, value):
    with pytest.raises(KnobError, match=key.replace(".", r"\.")):
        AlgorithmConfig().override({key: value})


def test_inconsistent_thresholds_rejected():
    with pytest.raises(KnobError, match="tau_k"):
        AlgorithmConfig().override({"memory.tau_m": 0.3, "memory.tau_k": 0.5})
    # one set, the other the descriptor's: checked once resolved
    with pytest.raises(KnobError, match="tau_k"):
        AlgorithmConfig().override({"memory.tau_k": 0.95}).resolved({"tau_m": 0.9})


def _corrupt_replies(agent, how: str, at_step: int) -> None:
    """Make ``agent`` answer image requests of ``at_step`` with a broken reply."""
    import dataclasses

    from cerpe.messages import ImageReply

    honest = agent.image_reply

    def reply(request):
        r = honest(request)
        if r is None or request.step != at_step:
            return r
        if how == "truncated":
            return dataclasses.replace(r, jpeg=r.jpeg[: len(r.jpeg) * 2 // 3])
        if how == "garbage":
            return dataclasses.replace(r, jpeg=bytes(range(256)) * 4)
        img = r.image_rgb()
        img = img[::2, ::2] if how == "half-size" else np.repeat(np.repeat(img, 2, axis=0), 2, axis=1)
        return ImageReply.from_image(r.sender, r.step, img, r.intrinsics)  # the full-size intrinsics

    agent.image_reply = reply


@pytest.mark.parametrize("how, fault", [("truncated", "truncated-jpeg"), ("half-size", "image-size-mismatch"),
                                        ("double-size", "image-size-mismatch"), ("garbage", "undecodable-jpeg")])
def test_broken_image_reply_is_counted_and_closes_that_pair_for_the_step(world, how, fault):
    team = _team(world)
    _corrupt_replies(team.agents[1], how, at_step=6)  # r1 answers r0's request of step 6 badly
    results = [team.step(*_inputs(world, t)) for t in range(8)]  # overlap window from step 5
    r0 = results[6].robots[0]
    assert r0.degradations == [f"msg:{fault}"]
    p = next(p for p in results[6].pairs if p.ego == "r0")
    assert p.gate_open and p.bytes_pair > 0  # the request was made and the reply paid for
    assert p.source == "propagated" and p.anchor_step == 5 and p.anchor_verdict == ""
    assert p.reason == f"reply-{fault}; unverified"
    q = next(p for p in results[6].pairs if p.ego == "r1")
    assert q.source == "direct"  # the other direction is untouched
    assert next(p for p in results[7].pairs if p.ego == "r0").source == "direct"
    assert all(r.degradations == [] for res in results if res.step != 6 for r in res.robots)


def test_received_view_checks_on_real_jpegs(world):
    from cerpe.algorithm.frames import jpeg_truncated, received_view
    from cerpe.messages import ImageReply

    K = world.intrinsics
    img = np.ascontiguousarray(np.tile(world.images[0][3], (4, 4, 1)))  # 128x96, real JPEG content
    big = (K.fx * 4, K.fy * 4, (K.cx + 0.5) * 4 - 0.5, (K.cy + 0.5) * 4 - 0.5)
    reply = ImageReply.from_image(1, 3, img, big)
    view, fault = received_view("r1", reply)
    assert fault == "" and view.image.shape == img.shape and view.key == ("r1", 3, "jpeg")
    assert (view.intrinsics.width, view.intrinsics.height, view.intrinsics.cx) == (128, 96, big[2])
    assert not jpeg_truncated(reply.jpeg)
    for cut in (10, len(reply.jpeg) // 3, len(reply.jpeg) - 2):
        assert jpeg_truncated(reply.jpeg[:cut])
    unknown = ImageReply.from_image(1, 3, img, (0.0, 0.0, 0.0, 0.0))  # no intrinsics: only the size is checked
    assert received_view("r1", unknown)[1] == ""
    tiny = ImageReply.from_image(1, 3, img[:4, :4], (0.0, 0.0, 0.0, 0.0))
    assert received_view("r1", tiny) == (None, "image-size-mismatch")

"""Cross-robot registration in the offline backbone (cerpe/backbones/offline/cross.py): registrations of a
collaborator view against the robot's own views on rendered and real frames, checked against ground truth;
the cascade (learned matcher only when the cheap one fails); bad input; roles handed in by the agent."""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from test_backbone_offline import K, Room, pose

from cerpe import geometry as G
from cerpe.protocols import View

ROOT = Path(__file__).resolve().parents[1]

# world poses: the own views look at the back wall; "near" is an easy collaborator, "wide" one 60 deg off
POSES = {"cur": pose((0, 0, 0), (0, 2, 0)), "kf": pose((-0.4, 0, 0.2), (0, 15, 0)),
         "prev": pose((0.05, 0, -0.05), (0, 1, 0)), "near": pose((-0.8, 0.1, 1.0), (3, 35, 0)),
         "wide": pose((-1.5, 0.2, 2.0), (8, 60, 5)), "left": pose((0, 0, 0), (0, -90, 0))}
ROLES = {"cur": "current", "left": "current", "kf": "keyframe", "prev": "previous"}


@pytest.fixture(scope="module")
def room() -> Room:
    return Room(0)


def view(room: Room, name: str, depth: bool = True, role: str | None = None) -> View:
    img, d = room.render(POSES[name])
    return View(("r0" if name in ROLES else "r1", name), img, K, d if depth else None,
                role=role or ROLES.get(name, "collaborator"))


def backbone(**cross):
    from cerpe.backbones.config import OfflineConfig
    from cerpe.backbones.offline import OfflineGeometryBackbone

    # 2048 keypoints, as test_backbone_offline's backbone: the image-only registrations need them here
    return OfflineGeometryBackbone(OfflineConfig(keypoints=2048, cross={"enabled": True, **cross}))


def errors(T: np.ndarray, T_gt: np.ndarray) -> tuple[float, float]:
    """(rotation deg, translation m) between two poses."""
    return float(np.degrees(G.e_rot(T, T_gt))), float(np.linalg.norm(T[:3, 3] - T_gt[:3, 3]))


def gt(names: list[str], via: int, k: int) -> np.ndarray:
    return G.se3_inverse(POSES[names[via]]) @ POSES[names[k]]


def test_registrations_through_current_previous_and_keyframe_match_ground_truth(room):
    names = ["cur", "kf", "prev", "near"]
    out = backbone(matcher="none").infer([view(room, n, depth=n != "near") for n in names])
    regs = out.registrations[3]
    assert sorted(r.via for r in regs) == [0, 1, 2]
    assert [r.inliers for r in regs] == sorted((r.inliers for r in regs), reverse=True)
    for r in regs:
        assert 50 <= r.inliers <= r.matches
        rot, trans = errors(r.T_via_cam, gt(names, r.via, 3))
        assert rot < 1.0 and trans < 0.15, (r.via, rot, trans)  # about 1.5 m between the cameras
    # the collaborator's pass pose follows the best registration through a placed view; metres
    assert out.valid.all() and out.metric_unit and out.reasons[3] == ""
    np.testing.assert_allclose(out.T_frame_cam[3], out.T_frame_cam[regs[0].via] @ regs[0].T_via_cam, atol=1e-9)
    assert not out.depth[3].any()  # collaborators are not part of the own reconstruction


def test_collaborator_seen_only_from_an_older_keyframe_is_registered_through_it(room):
    """The current view looks at the left wall, the keyframe and the collaborator at the back wall: the only
    registration is through the keyframe, which the pass cannot place (the algorithm then composes the
    estimate through the robot's odometry)."""
    names = ["left", "kf", "near"]
    out = backbone(matcher="none").infer([view(room, "left"), view(room, "kf"), view(room, "near", depth=False)])
    (r,) = out.registrations[2]
    assert r.via == 1
    rot, trans = errors(r.T_via_cam, gt(names, 1, 2))
    assert rot < 1.0 and trans < 0.15
    assert not out.valid[1] and not out.valid[2] and out.reasons[2] == "via-unplaced"
    assert np.all(np.isnan(out.T_frame_cam[2]))


class SpyMatcher:
    """The real learned matcher (LighterGlue over XFeat), counting its calls."""

    def __init__(self) -> None:
        from cerpe.backbones.config import CrossConfig
        from cerpe.backbones.offline.cross import LearnedMatcher

        self.inner = LearnedMatcher(CrossConfig(matcher="xfeat"))
        self.calls: list[str] = []

    def features(self, p, s):
        self.calls.append("features")
        return self.inner.features(p, s)

    def match(self, f0, f1):
        self.calls.append("match")
        return self.inner.match(f0, f1)


def test_the_learned_matcher_runs_only_when_the_cheap_one_fails(room):
    from cerpe.backbones.config import OfflineConfig
    from cerpe.backbones.offline import OfflineGeometryBackbone

    spy = SpyMatcher()
    bb = OfflineGeometryBackbone(OfflineConfig(cross={"enabled": True, "matcher": "xfeat", "max_views": 2}),
                                 learned=spy)
    own = [view(room, "cur"), view(room, "kf"), view(room, "prev")]
    out = bb.infer(own + [view(room, "near", depth=False)])
    assert spy.calls == [] and len(out.registrations[3]) == 3  # mutual-NN + P3P were enough
    out = bb.infer(own + [view(room, "wide", depth=False)])
    assert spy.calls.count("match") == 2  # max_views own views, those with most mutual-NN matches
    assert bb.counts["cross-learned"] == 1 and bb.counts["cross-learned-pairs"] == 2
    names = ["cur", "kf", "prev", "wide"]
    assert out.registrations[3] and out.valid[3]
    for r in out.registrations[3]:
        rot, trans = errors(r.T_via_cam, gt(names, r.via, 3))
        assert r.inliers >= 50 and rot < 1.0 and trans < 0.15, (r.via, rot, trans)
    # without the learned stage the wide view is not registered (and a reason says why)
    out = backbone(matcher="none").infer(own + [view(room, "wide", depth=False)])
    assert 3 not in out.registrations and not out.valid[3] and out.reasons[3] in ("few-inliers", "few-matches")


def test_without_depth_the_essential_matrix_registers_against_the_own_views_in_the_pass_unit(room):
    names = ["cur", "kf", "near"]
    out = backbone(matcher="none").infer([view(room, n, depth=False) for n in names])
    assert not out.metric_unit and out.valid.all(), out.reasons
    regs = out.registrations[2]
    assert sorted(r.via for r in regs) == [0, 1]
    # one unit in the pass: the keyframe's translation and the registrations' scale the same way
    unit = np.linalg.norm(out.T_frame_cam[1][:3, 3]) / np.linalg.norm(gt(names, 0, 1)[:3, 3])
    for r in regs:
        T_gt = gt(names, r.via, 2)
        assert r.inliers >= 50 and np.degrees(G.e_rot(r.T_via_cam, T_gt)) < 1.0
        t, t_gt = r.T_via_cam[:3, 3], T_gt[:3, 3]
        assert np.degrees(np.arccos(t @ t_gt / np.linalg.norm(t) / np.linalg.norm(t_gt))) < 5.0
        assert np.linalg.norm(t) / np.linalg.norm(t_gt) == pytest.approx(unit, rel=0.1)


def test_bad_collaborators_are_left_unplaced_with_a_reason(room):
    bb = backbone(matcher="none")
    own = [view(room, "cur"), view(room, "kf")]
    img = room.render(POSES["near"])[0]
    out = bb.infer(own + [View(("r1", 0), img, None, role="collaborator"),
                          View(("r1", 1), np.full_like(img, 128), K, role="collaborator")])
    assert out.valid.tolist() == [True, True, False, False] and not out.registrations
    assert out.reasons[2:] == ["no-intrinsics", "low-texture"]
    # an image of another size than its intrinsics, one too small to encode, one not RGB: unplaced, counted,
    # and the registration of a good collaborator after them keeps its index
    near = view(room, "near", depth=False)
    out = bb.infer(own + [View(("r1", 2), img[:200, :300], K, role="collaborator"),
                          View(("r1", 3), img[:16, :16], K, role="collaborator"),
                          View(("r1", 4), img[..., 0], K, role="collaborator"), near])
    assert out.reasons[2:5] == ["image-size-mismatch", "bad-image", "bad-image"] and out.reasons[5] == ""
    assert out.valid.tolist() == [True, True, False, False, False, True] and list(out.registrations) == [5]
    assert {r.via for r in out.registrations[5]} == {0, 1} and np.isnan(out.T_frame_cam[2:5]).all()
    assert len(out.depth) == len(out.memos) == 6 and out.depth[2].shape == (200, 300)
    assert bb.counts["cross-image-size-mismatch"] == 1 and bb.counts["cross-bad-image"] == 2
    with pytest.raises(Exception, match="view 1"):  # an own view that cannot be encoded stays an error
        bb.infer([own[0], View(("r0", "x"), img[:16, :16], K, role="keyframe")])


def test_features_evicted_from_every_cache_give_the_same_registrations(room, monkeypatch):
    """A keyframe whose XFeat features, matches and learned features are no longer cached (caches of
    size 0) is recomputed from its pixels: the same passes, registration for registration."""
    from cerpe.backbones.config import OfflineConfig
    from cerpe.backbones.offline import OfflineGeometryBackbone
    from cerpe.backbones.offline import backbone as bb_mod
    from cerpe.backbones.offline import cross as cross_mod
    from cerpe.backbones.xfeat import XFeatEncoder

    warm = backbone(matcher="xfeat")
    monkeypatch.setattr(bb_mod, "MATCH_CACHE_SIZE", 0)
    monkeypatch.setattr(cross_mod, "FEATURE_CACHE_SIZE", 0)
    conf = OfflineConfig(keypoints=2048, cross={"enabled": True, "matcher": "xfeat"})
    tiny = OfflineGeometryBackbone(conf, encoder=XFeatEncoder(conf.keypoints, cache_size=0))
    passes = [[view(room, "kf")], [view(room, "cur"), view(room, "kf"), view(room, "near", depth=False)],
              [view(room, "prev"), view(room, "kf"), view(room, "cur"), view(room, "wide", depth=False)]]
    for views in passes:
        a, b = warm.infer(views), tiny.infer(views)
        assert a.valid.tolist() == b.valid.tolist() and a.reasons == b.reasons
        np.testing.assert_array_equal(a.T_frame_cam, b.T_frame_cam)
        assert a.registrations.keys() == b.registrations.keys()
        for k, regs in a.registrations.items():
            assert [(r.via, r.inliers, r.matches) for r in regs] == \
                [(r.via, r.inliers, r.matches) for r in b.registrations[k]]
            for r, s in zip(regs, b.registrations[k]):
                np.testing.assert_array_equal(r.T_via_cam, s.T_via_cam)
    assert tiny.encoder.n_encoded > 3 and len(tiny.matcher.cache) == 0  # really recomputed


def test_registrations_on_real_rgbd_frames_match_motion_capture(shared_data):
    """TUM fr1/xyz (Kinect depth, motion capture): frame 3, JPEG-encoded as a reply would carry it,
    registered against the current (7), previous (6) and keyframe (0) views."""
    from cerpe.datasets import load_setting
    from cerpe.messages import ImageReply

    (enc,) = load_setting(ROOT / "datasets_manifest" / "dev-tum-fr1-xyz.yaml").encounters
    a = enc.robots[0]
    frames = [7, 0, 6]
    views = [View(("a", t), a.image(t), a.intrinsics, a.depth_m(t), role=role)
             for t, role in zip(frames, ("current", "keyframe", "previous"))]
    jpeg = ImageReply.from_image(1, 3, a.image(3), (a.intrinsics.fx, a.intrinsics.fy, a.intrinsics.cx,
                                                    a.intrinsics.cy), quality=90).image_rgb()
    views.append(View(("b", 3, "jpeg"), jpeg, a.intrinsics, role="collaborator"))
    out = backbone(matcher="none").infer(views)
    regs = out.registrations[3]
    assert sorted(r.via for r in regs) == [0, 1, 2]
    for r in regs:
        T_gt = G.se3_inverse(a.T_world_cam[frames[r.via]]) @ a.T_world_cam[3]
        rot, trans = errors(r.T_via_cam, T_gt)
        assert rot < 1.0 and trans < 0.03, (r.via, rot, trans)


def test_the_agent_hands_every_view_its_role():
    """current, keyframes, previous frame, collaborators: the roles the backbone sees."""
    from gt_backbone import GTBackbone, OverlapDescriptor, SensorDepthDouble, make_world

    from cerpe.algorithm import AlgorithmConfig, Team

    class RoleSpy(GTBackbone):
        roles: list = []

        def infer(self, views):
            self.roles.append([(v.key, v.role) for v in views])
            return super().infer(views)

    world = make_world(2, 8, seed=1)
    bb = RoleSpy(world, seed=1)
    team = Team(world.robot_ids, OverlapDescriptor(world), bb, SensorDepthDouble(), AlgorithmConfig().override({"scale.min_pixels": 20}))
    list(team.run_encounter(world.to_encounter()))
    seen = {role for call in bb.roles for _, role in call}
    assert seen == {"current", "keyframe", "previous", "collaborator"}
    for call in bb.roles:
        assert call[0][1] == "current" and all(r != "current" for _, r in call[1:])
        for key, role in call:
            assert (role == "collaborator") == (len(key) == 3)  # received images are keyed (robot, step, "jpeg")


def test_cross_registration_by_default_only_where_own_views_have_no_depth(monkeypatch):
    """``cross.enabled="without-depth"`` (the default): RGB-only passes register collaborators
    apart; with depth on the own views they join the joint reconstruction (the paper's pass)."""
    from cerpe.backbones.config import OfflineConfig
    from cerpe.backbones.offline import OfflineGeometryBackbone
    from cerpe.knobs import KnobError
    from cerpe.protocols import View

    bb = OfflineGeometryBackbone()
    d = np.ones((4, 4))
    own_rgb = [View("a", None, None, None, role="current"), View("b", None, None, None, role="keyframe")]
    collab = View("c", None, None, d, role="collaborator")  # a collaborator's depth does not count
    assert bb._cross_on(own_rgb + [collab])
    assert not bb._cross_on([View("a", None, None, d, role="current")] + own_rgb[1:] + [collab])
    assert OfflineGeometryBackbone(OfflineConfig(cross={"enabled": True}))._cross_on([View("a", None, None, d)])
    assert not OfflineGeometryBackbone(OfflineConfig(cross={"enabled": False}))._cross_on(own_rgb)
    with pytest.raises(KnobError, match="cross.enabled"):
        OfflineConfig(cross={"enabled": "sometimes"})

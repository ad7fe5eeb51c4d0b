"""The appearance check of collaborator placements (cerpe/backbones/offline/cross.py ``check_appearance``):
a placement the keypoints allow but the images contradict (the collaborator put 1 m ahead of the robot,
turned alike, as repeated or mirrored structure does) is dropped and counted, the true one kept; end to
end, the agent counts such a view as ``direct:appearance-mismatch`` and has no direct estimate that step."""
from __future__ import annotations

from collections import Counter

import numpy as np
import pytest
from gt_backbone import GTBackbone, OverlapDescriptor, SensorDepthDouble, make_world
from test_backbone_offline import K, Room, pose

from cerpe import geometry as G
from cerpe.algorithm import DEGRADATIONS, AlgorithmConfig, Team
from cerpe.protocols import REASON_APPEARANCE, View

POSES = {"cur": pose((0, 0, 0), (0, 2, 0)), "near": pose((-0.8, 0.1, 1.0), (3, 35, 0))}


@pytest.fixture(scope="module")
def room() -> Room:
    return Room(0)


def pass_of(images, depth_m, **cross):
    """A pass over the current view ``images[0]`` (with the depth prior ``depth_m``) and a collaborator
    ``images[1]`` (without), as ``infer`` builds it; ``cross``: the backbone's ``cross`` settings."""
    from cerpe.backbones.config import OfflineConfig
    from cerpe.backbones.offline import OfflineGeometryBackbone
    from cerpe.backbones.offline.context import Pass
    from cerpe.backbones.offline.matching import pinhole_camera

    bb = OfflineGeometryBackbone(OfflineConfig(cross=cross))
    views = [View(("r0", 0), images[0], K, depth_m, role="current"),
             View(("r1", 0, "jpeg"), images[1], K, None, role="collaborator")]
    feats = [bb.encoder.encode(v) for v in views]
    return Pass(views=views, feats=feats, Ks=[K.K, K.K], cams=[pinhole_camera(K)] * 2,
                low_tex=[False, False], conf=bb.conf, matcher=bb.matcher, memos=[None, None])


def make_pass(room: Room, **cross):
    """The pass of the room seen from ``POSES["cur"]`` (with depth) and ``POSES["near"]`` (the collaborator)."""
    (img0, d0), (img1, _) = room.render(POSES["cur"]), room.render(POSES["near"])
    return pass_of([img0, img1], d0, **cross)


TRUE = G.se3_inverse(POSES["cur"]) @ POSES["near"]           # T_cur_near
AHEAD = pose((0.0, 0.0, 1.0), (0, 0, 0))                       # the wrong start: 1 m ahead, turned alike


def test_true_placement_is_kept_and_one_ahead_turned_alike_is_rejected_and_counted(room):
    from cerpe.backbones.offline.cross import check_appearance

    p = make_pass(room)
    assert check_appearance(p, 0, 1, TRUE, 20) == ""
    assert p.counts["cross-appearance-checked"] == 1 and p.counts["cross-appearance-rejected"] == 0
    assert check_appearance(p, 0, 1, AHEAD, 20) == REASON_APPEARANCE
    assert p.counts["cross-appearance-checked"] == 2 and p.counts["cross-appearance-rejected"] == 1
    # enough keypoint inliers: the keypoints alone support it, not judged
    assert check_appearance(p, 0, 1, AHEAD, 40) == "" and p.counts["cross-appearance-checked"] == 2


def test_unjudged_placements_pass_and_the_check_can_be_switched_off(room):
    from cerpe.backbones.offline.cross import check_appearance

    p = make_pass(room)
    assert check_appearance(p, 0, 1, pose((0, 0, 0), (0, 180, 0)), 20) == ""  # nothing of view 0 in sight
    assert check_appearance(p, 0, 1, np.full((4, 4), np.nan), 20) == ""
    assert p.counts["cross-appearance-checked"] == 0
    assert check_appearance(make_pass(room, appearance_check=False), 0, 1, AHEAD, 20) == ""


def test_a_joint_placement_that_fails_leaves_the_reconstruction_with_its_reason(room):
    from cerpe.backbones.offline.context import Recon
    from cerpe.backbones.offline.cross import check_joint_placements

    p = make_pass(room)
    for T, kept in ((TRUE, True), (AHEAD, False)):
        rec = Recon(X=np.zeros((3, 3)), T={0: np.eye(4), 1: T}, obs={1: (np.arange(3), np.arange(3))}, metric=True)
        reasons = ["", ""]
        check_joint_placements(p, rec, [1], reasons)
        assert (1 in rec.T, 1 in rec.obs, reasons[1]) == ((True, True, "") if kept else (False, False, REASON_APPEARANCE))
    rec = Recon(X=np.zeros((3, 3)), T={0: np.eye(4), 1: AHEAD}, metric=False)  # image-only unit: not judged
    check_joint_placements(p, rec, [1], ["", ""])
    assert 1 in rec.T


def test_the_offline_backbone_drops_a_contradicted_collaborator(room, monkeypatch):
    """The joint pass places the collaborator wrongly (injected into the placement): it comes back unplaced."""
    from cerpe.backbones.config import OfflineConfig
    from cerpe.backbones.offline import OfflineGeometryBackbone
    from cerpe.backbones.offline import backbone as bb_mod
    from cerpe.backbones.offline import cross as cross_mod

    views = [View(("r0", n), *room.render(POSES["cur"] @ pose((0.02 * n, 0, 0))), role="current" if n == 0 else "keyframe")
             for n in range(2)]
    views = [View(v.key, v.image, K, v.intrinsics, role=v.role) for v in views]  # (image, depth) -> K, depth
    img1, _ = room.render(POSES["near"])
    views.append(View(("r1", 0, "jpeg"), img1, K, None, role="collaborator"))
    conf = OfflineConfig(cross={"enabled": False})
    monkeypatch.setattr(cross_mod, "APPEARANCE_MAX_INLIERS", 10**6)  # judge it, however many inliers
    bb = OfflineGeometryBackbone(conf)
    out = bb.infer(views)
    assert out.valid[2] and out.reasons[2] == ""  # the true placement passes
    T_true = out.T_frame_cam[2]
    assert G.e_rot(T_true, G.se3_inverse(views_pose(0)) @ POSES["near"]) < 0.02

    real = bb_mod._solve_once

    def wrong(p, metric):
        rec, reasons = real(p, metric)
        if rec is not None and 2 in rec.T:
            rec.T[2] = rec.T[0] @ AHEAD
        return rec, reasons

    monkeypatch.setattr(bb_mod, "_solve_once", wrong)
    bb = OfflineGeometryBackbone(conf)
    out = bb.infer(views)
    assert not out.valid[2] and out.reasons[2] == REASON_APPEARANCE and np.all(np.isnan(out.T_frame_cam[2]))
    assert out.valid[0] and out.valid[1]  # the own views are untouched
    assert bb.counts["cross-appearance-rejected"] == 1


def views_pose(n: int) -> np.ndarray:
    return POSES["cur"] @ pose((0.02 * n, 0, 0))


class ContradictedBackbone(GTBackbone):
    """GTBackbone whose pass at the given (ego, step) says the collaborator's placement was contradicted."""

    def __init__(self, world, at: set, **kw) -> None:
        super().__init__(world, **kw)
        self.at = at

    def infer(self, views):
        out = super().infer(views)
        for k, v in enumerate(views):
            if len(v.key) == 3 and views[0].key in self.at:
                out.valid[k], out.reasons[k] = False, REASON_APPEARANCE
                out.T_frame_cam[k] = np.nan
        return out


def test_the_agent_counts_a_contradicted_placement_and_has_no_direct_estimate():
    world = make_world(2, 40, seed=1)  # overlap windows 5-9 and 25-29
    bb = ContradictedBackbone(world, {("r0", 27)}, seed=1)
    team = Team(world.robot_ids, OverlapDescriptor(world), bb, SensorDepthDouble(), AlgorithmConfig().override({"scale.min_pixels": 20}))
    results = list(team.run_encounter(world.to_encounter()))
    P = {res.step: next(p for p in res.pairs if p.ego == "r0") for res in results}
    deg = Counter(d for res in results for r in res.robots if r.robot == "r0" for d in r.degradations)
    assert "direct:appearance-mismatch" in DEGRADATIONS
    assert deg["direct:appearance-mismatch"] == 1
    p = P[27]
    assert p.gate_open and p.T_direct is None and p.anchor_verdict == ""
    assert p.source == "propagated" and p.anchor_step == 26 and p.reason.startswith("appearance-mismatch")
    assert P[28].source == "direct"


def layout_passes(seed: int):
    """Two passes over images with one layout (bright above, dark below, as sky and road) and a
    fronto-parallel depth prior: ``(other, same)``, the collaborator with unrelated texture / the same."""
    import cv2

    rng = np.random.default_rng(seed)
    H, W = K.height, K.width
    layout = np.linspace(220.0, 40.0, H)[:, None] * np.ones((1, W))
    tex = [cv2.GaussianBlur(rng.normal(0, 25, (H, W)), (0, 0), 1.5) for _ in range(2)]

    def rgb(g):
        return np.repeat(np.clip(g, 0, 255).astype(np.uint8)[..., None], 3, axis=2)

    depth = np.full((H, W), 4.0, np.float32)
    return (pass_of([rgb(layout + tex[0]), rgb(layout + tex[1])], depth),
            pass_of([rgb(layout + tex[0]), rgb(layout + tex[0])], depth))


def test_the_high_pass_compares_texture_not_the_layout_every_camera_held_alike_shares():
    """Two images with the same layout (bright above, dark below) and unrelated texture: the plain
    correlation is high, the high-passed one near zero; with the same texture both are high."""
    from cerpe.backbones.offline.vote import photometric_agreement

    other, same = layout_passes(3)
    I4 = np.eye(4)
    _, plain = photometric_agreement(other, 0, 1, I4)
    _, high = photometric_agreement(other, 0, 1, I4, highpass_px=12.0)
    assert plain > 0.7 and abs(high) < 0.2
    assert photometric_agreement(same, 0, 1, I4, highpass_px=12.0)[1] > 0.9


def test_a_placement_must_agree_in_texture_too_not_only_in_layout(monkeypatch):
    """Only the layout agrees: the plain correlation passes, the high-passed one fails, the placement is
    dropped and counted; with the high pass off it is kept, and with the same texture it is kept."""
    from cerpe.backbones.offline import cross as cross_mod
    from cerpe.backbones.offline.cross import check_appearance

    p, same = layout_passes(5)
    assert check_appearance(p, 0, 1, np.eye(4), 20) == REASON_APPEARANCE
    assert p.counts["cross-appearance-checked"] == 1 and p.counts["cross-appearance-rejected"] == 1
    monkeypatch.setattr(cross_mod, "APPEARANCE_HIGHPASS_PX", 0.0)
    assert check_appearance(p, 0, 1, np.eye(4), 20) == ""
    assert check_appearance(same, 0, 1, np.eye(4), 20) == ""

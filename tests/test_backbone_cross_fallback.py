"""The fallback of the offline backbone (``cross.fallback``): on RGB-D passes a collaborator the joint
pass left unplaced is registered apart (both stages) only when the robot asks (``View.try_hard``); the
agent asks while it holds no anchor of the sender, ever more rarely while nothing places
(:func:`cerpe.algorithm.policy.try_hard`)."""
from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from test_backbone_cross import SpyMatcher, errors, gt, view

from cerpe.backbones.config import OfflineConfig
from cerpe.backbones.offline import OfflineGeometryBackbone
from cerpe.knobs import KnobError

NAMES = ["cur", "kf", "prev", "wide"]


@pytest.fixture(scope="module")
def room():
    from test_backbone_offline import Room

    return Room(0)


def rgbd_pass(room, hard, **cross):
    """The default backbone (cross off: own views with depth) over three own views and the "wide"
    collaborator (60 deg off), asked to try hard or not; returns (output, learned-matcher spy, backbone)."""
    spy = SpyMatcher()
    bb = OfflineGeometryBackbone(OfflineConfig(cross=cross), learned=spy)
    views = [view(room, n) for n in NAMES[:3]] + [dataclasses.replace(view(room, "wide", depth=False),
                                                                       try_hard=hard)]
    return bb.infer(views), spy, bb


def test_a_collaborator_the_joint_pass_left_is_registered_apart_when_asked(room):
    off, spy_off, _ = rgbd_pass(room, True, fallback=False)
    assert not off.valid[3] and off.reasons[3] and spy_off.calls == []  # the joint pass alone cannot place it
    out, spy, bb = rgbd_pass(room, True)
    assert out.valid[3] and out.reasons[3] == "" and out.metric_unit
    assert spy.calls.count("match") == 1 and bb.counts["cross-fallback-placed"] == 1  # fallback_max_views
    assert bb.counts["cross-appearance-checked"] == 1  # judged, whatever its inliers
    for r in out.registrations[3]:
        rot, trans = errors(r.T_via_cam, gt(NAMES, r.via, 3))
        assert r.inliers >= 50 and rot < 1.0 and trans < 0.15, (r.via, rot, trans)
    best = out.registrations[3][0]
    np.testing.assert_allclose(out.T_frame_cam[3], out.T_frame_cam[best.via] @ best.T_via_cam, atol=1e-9)


def test_a_fallback_needs_min_inliers_pnp_from_either_stage(room):
    out, spy, bb = rgbd_pass(room, True, min_inliers_pnp=10_000)
    assert not out.valid[3] and out.reasons[3] and spy.calls.count("match") == 1
    assert bb.counts["cross-fallback-none"] == 1 and 3 not in out.registrations


def test_a_collaborator_not_asked_for_gets_no_fallback(room):
    out, spy, bb = rgbd_pass(room, False)
    assert not out.valid[3] and out.reasons[3] and spy.calls == []
    assert 3 not in out.registrations and bb.counts["cross-fallback-placed"] == 0


def test_the_fallback_key_is_checked():
    with pytest.raises(KnobError, match="cross.fallback"):
        OfflineConfig(cross={"fallback": "yes"})
    with pytest.raises(KnobError, match="cross.min_inliers_pnp"):
        OfflineConfig(cross={"min_inliers_pnp": 0})


def test_the_agent_asks_to_try_hard_until_the_pair_is_anchored():
    """Collaborator views arrive with try_hard until the pair has a verified anchor, without after."""
    from gt_backbone import GTBackbone, OverlapDescriptor, SensorDepthDouble, make_world

    from cerpe.algorithm import AlgorithmConfig, Team

    class HardSpy(GTBackbone):
        def infer(self, views):
            self.seen += [(v.key[0], v.key[1], v.try_hard) for v in views if v.role == "collaborator"]
            return super().infer(views)

    def run(**conf) -> list:
        world = make_world(2, 16, seed=1)
        bb = HardSpy(world, seed=1)
        bb.seen = []
        team = Team(world.robot_ids, OverlapDescriptor(world), bb, SensorDepthDouble(),
                    AlgorithmConfig().override({"scale.min_pixels": 20, **conf}))
        list(team.run_encounter(world.to_encounter()))
        return sorted(bb.seen)

    seen = run()
    for sender in {s for s, _, _ in seen}:
        flags = [h for s, _, h in seen if s == sender]
        assert flags[0] and not flags[-1], flags  # first contact asked for, the anchored pair not
        assert flags == sorted(flags, reverse=True), flags  # once anchored, never again in this world
    # asking for every image, gate or not (the first ones before the gate opens, when nothing has missed
    # yet): only gated ones, those the paper's policy asks for, may try hard
    always = run(**{"policy.mode": "always"})
    gated = {(s, t) for s, t, _ in seen}
    assert len(always) > len(seen) and min(t for _, t, _ in always) < min(t for _, t in gated)
    assert all((s, t) in gated for s, t, h in always if h)

"""Blank frames and backbone memos: what a robot keeps of a frame, and what it never keeps.

Blank (black, white, constant grey) frames in the middle of a sequence must be
counted, never become keyframes or the tracking reference, and leave the
odometry of the frames after them as it would be without them. A backbone's memo
of a frame comes back with that frame only, and never across ``Team.reset()``.
"""
from __future__ import annotations

from collections import Counter

import numpy as np
import pytest

from cerpe.algorithm import DEGRADATIONS, AlgorithmConfig, Team
from cerpe.reasons import known_degradation as known
from cerpe.protocols import FrameContext, View
from cerpe.transport import Channel
from gt_backbone import GTBackbone, OverlapDescriptor, SensorDepthDouble, make_world

CFG = AlgorithmConfig().override({"scale.min_pixels": 20})
BLANK = {10: 0, 11: 255, 12: 128}  # r0's frames at these steps: black, white, constant grey


class BlindBackbone(GTBackbone):
    """Places a view without texture 14 cm off its true pose, as a backbone that cannot see it might."""

    def infer(self, views):
        out = super().infer(views)
        for s, v in enumerate(views):
            if out.valid[s] and np.ptp(v.image) == 0:
                out.T_frame_cam[s][:3, 3] += 0.14
        return out


def _with_blank(world, blank: dict[int, int]):
    """``world``'s encounter with r0's frames at ``blank``'s steps set to one grey level (world untouched)."""
    enc = world.to_encounter()
    enc.robots[0].images = [np.full_like(img, blank[t]) if t in blank else img
                            for t, img in enumerate(world.images[0])]
    return enc


def _run(world, blank: dict[int, int], backbone=None, descriptor=None, channel=None):
    enc = _with_blank(world, blank)
    backbone = backbone or BlindBackbone(world, seed=1)
    team = Team(world.robot_ids, descriptor or OverlapDescriptor(world), backbone, SensorDepthDouble(), CFG,
                channel)
    return team, backbone, list(team.run_encounter(enc))


def test_blank_frames_are_counted_never_kept_and_do_not_move_the_odometry():
    world = make_world(2, 24, seed=11)
    team, bb, results = _run(world, BLANK)
    _, _, plain = _run(world, {})
    for t in BLANK:
        r0, r1 = results[t].robots
        assert r0.degradations.count("frame:blank") == 1 and not r0.keyframe
        assert r0.n_keyframes == results[9].robots[0].n_keyframes
        np.testing.assert_array_equal(r0.T_odom_cam, results[9].robots[0].T_odom_cam)  # constant position
        assert "descriptor:other-zero-norm" in r1.degradations  # the zero descriptor went out
        assert all(not p.gate_open for p in results[t].pairs)
    # no pass of r0 saw a blank frame: not as current view (no pass at all), keyframe or previous frame
    blank_keys = {("r0", t) for t in BLANK}
    assert not any(k in blank_keys for keys in bb.calls for k in keys)
    assert len(bb.calls) == 2 * 24 - len(BLANK)
    first_after = next(keys for keys in bb.calls if keys[0] == ("r0", 13))
    assert ("r0", 9) in first_after  # chained through the last good frame
    # after the blank frames the odometry is the one of the run without them, and exact
    for t in range(13, 24):
        np.testing.assert_allclose(results[t].robots[0].T_odom_cam, plain[t].robots[0].T_odom_cam, atol=1e-6)
        np.testing.assert_allclose(results[t].robots[0].T_odom_cam, world.gt_odometry(0, t), atol=1e-6)
    assert not any("frame:blank" in r.degradations for res in plain for r in res.robots)


class FlaggingDescriptor(OverlapDescriptor):
    """Says ``low-texture`` for some views, although their pixels are textured."""

    def __init__(self, world, low_texture):
        super().__init__(world)
        self.low_texture, self.asked = set(low_texture), []

    def flags(self, view):
        self.asked.append(view)
        return frozenset({"low-texture"}) if view.key in self.low_texture else frozenset()


def test_the_descriptors_low_texture_flag_makes_a_frame_blank():
    world = make_world(2, 12, seed=2)
    desc = FlaggingDescriptor(world, [("r1", 7)])
    _, bb, results = _run(world, {}, GTBackbone(world, seed=1), desc)
    assert all(isinstance(v, View) for v in desc.asked) and len(desc.asked) == 2 * 12
    r1 = results[7].robots[1]
    assert r1.degradations == ["frame:blank"] and not r1.keyframe
    assert "descriptor:other-zero-norm" in results[7].robots[0].degradations
    assert not any(("r1", 7) in keys for keys in bb.calls)


def test_blank_std_is_the_one_threshold(monkeypatch):
    from cerpe.algorithm import agent as agent_mod

    world = make_world(2, 14, seed=3)
    enc = _with_blank(world, {8: 40})
    res = list(Team(world.robot_ids, OverlapDescriptor(world), GTBackbone(world), SensorDepthDouble(),
                    AlgorithmConfig().override({"scale.min_pixels": 20})).run_encounter(enc))
    assert "frame:blank" in res[8].robots[0].degradations
    monkeypatch.setattr(agent_mod, "BLANK_STD", 0.0)  # 0: only flags and zero descriptors count
    res = list(Team(world.robot_ids, OverlapDescriptor(world), GTBackbone(world), SensorDepthDouble(),
                    AlgorithmConfig().override({"scale.min_pixels": 20})).run_encounter(enc))
    assert "frame:blank" not in res[8].robots[0].degradations


class MemoBackbone(GTBackbone):
    """Emits a memo for the current view and checks the memos that come back."""

    def __init__(self, world, **kw):
        super().__init__(world, **kw)
        self.tag = "A"
        self.seen: list[tuple] = []  # (current key, view key, memo)

    def infer(self, views):
        for v in views:
            self.seen.append((views[0].key, v.key, v.memo))
        out = super().infer(views)
        out.memos = [{"key": views[0].key, "tag": self.tag}] + [None] * (len(views) - 1)
        return out


def test_memos_come_back_with_their_own_views_only_and_not_across_reset():
    world = make_world(2, 20, seed=4)
    bb = MemoBackbone(world, seed=1)
    team = Team(world.robot_ids, OverlapDescriptor(world), bb, SensorDepthDouble(), CFG)
    enc = world.to_encounter()
    for tag in ("A", "B"):
        bb.tag, bb.seen = tag, []
        results = list(team.run_encounter(enc))
        kf = {r: [res.step for res in results for x in res.robots if x.robot == r and x.keyframe] for r in "r0 r1".split()}
        handed_back = 0
        for cur, key, memo in bb.seen:
            if key == cur or len(key) == 3:  # the current view and received images carry none
                assert memo is None, (cur, key)
            else:  # a robot's own earlier frame: keyframe or previous frame, with its own memo
                assert key[0] == cur[0] and memo == {"key": key, "tag": tag}, (cur, key, memo)
                handed_back += 1
        assert handed_back > 40
        # previous frames that are not keyframes came back too
        assert any(len(key) == 2 and key != cur and key[1] not in kf[key[0]] for cur, key, _ in bb.seen)
        # the first pass of each robot after reset has nothing from before
        assert [k for c, k, _ in bb.seen if c == ("r0", 0)] == [("r0", 0)]


def test_every_counted_degradation_has_a_documented_name():
    world = make_world(3, 24, seed=5, windows={(0, 1): [(3, 8)], (0, 2): [(10, 15)], (1, 2): [(10, 15)]})
    _, _, results = _run(world, BLANK, channel=Channel(p_drop=0.1, p_garble=0.1, seed=1))
    names = Counter(d for res in results for r in res.robots for d in r.degradations)
    assert {"frame:blank", "msg:lost", "msg:garbled"} <= set(names)
    assert all(known(n) for n in names), [n for n in names if not known(n)]
    assert all(v for v in DEGRADATIONS.values())


def test_blank_frames_with_the_offline_backbone():
    """Real plug-ins on a ray-cast room: black/white/grey frames are counted, not kept, and the frame
    after them is where it would be without them."""
    from cerpe.backbones.build import build_plugins
    from test_backbone_offline import K, Room, pose

    room = Room(0)
    pl = build_plugins(depth="dataset")
    frames = [room.render(pose((0.06 * t, 0, 0.08 * t), (0, 1.5 * t, 0))) for t in range(9)]
    blank = {3: 0, 4: 255, 5: 128}

    def run(with_blank):
        team = Team(["a"], pl.descriptor, pl.backbone, pl.depth, AlgorithmConfig().override({"gate.tau": 0.3, "memory.tau_m": 0.9, "memory.tau_k": 0.2, "memory.delta_k": 2}))
        out = []
        for t, (img, depth) in enumerate(frames):
            if with_blank and t in blank:
                img = np.full_like(img, blank[t])
            out.append(team.step([img], [FrameContext("a", t, K, depth)]).robots[0])
        return team, out

    team, got = run(True)
    _, plain = run(False)
    for t in blank:
        assert got[t].degradations == ["frame:blank"] and not got[t].keyframe
        np.testing.assert_array_equal(got[t].T_odom_cam, got[2].T_odom_cam)
    assert not any(kf.step in blank for kf in team.agent("a").memory)
    for t in (6, 7, 8):
        assert np.linalg.norm(got[t].T_odom_cam[:3, 3] - plain[t].T_odom_cam[:3, 3]) < 0.005

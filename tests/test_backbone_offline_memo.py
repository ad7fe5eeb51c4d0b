"""The offline backbone keeps no state between passes: what it remembers about a view travels in
the view's memo, and a pass over given views (and memos) gives the same bits whatever ran before."""
from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from cerpe import geometry as G
from cerpe.protocols import View
from test_backbone_offline import K, Room, _blocks, grid_mask_image, pose


def _frames(room: Room, robot: str, poses: list[np.ndarray], patch_seed: int = 11) -> list[View]:
    """Views of ``room`` with a textured object 2 m away moving 24 px right per frame."""
    patch = _blocks(patch_seed, (100, 120), 6)
    views = []
    for k, T in enumerate(poses):
        img, d = (a.copy() for a in room.render(T))
        x0 = 40 + 24 * k
        img[60:160, x0:x0 + 120], d[60:160, x0:x0 + 120] = patch, 2.0
        views.append(View((robot, k), img, K, depth_m=d))
    return views


def _walk(bb, views: list[View]) -> list:
    """Passes ``[t] + [t-1 .. 0]`` for t = 1.., older views handed back with their memos (as a robot does)."""
    memos: dict = {}
    outs = []
    for t in range(1, len(views)):
        older = [dataclasses.replace(views[k], memo=memos.get(views[k].key)) for k in range(t - 1, -1, -1)]
        out = bb.infer([views[t]] + older)
        memos[views[t].key] = out.memos[0]
        outs.append(out)
    return outs


def _assert_same(a, b) -> None:
    assert np.array_equal(a.T_frame_cam, b.T_frame_cam, equal_nan=True)
    assert a.valid.tolist() == b.valid.tolist() and a.reasons == b.reasons
    assert (a.reference, a.metric_unit) == (b.reference, b.metric_unit)
    for x, y in zip(a.depth + a.depth_conf, b.depth + b.depth_conf):
        assert np.array_equal(x, y)
    ma, mb = a.memos[0], b.memos[0]
    assert (ma is None) == (mb is None)
    if ma is not None:
        assert ma["image"] == mb["image"]
        assert [k for k, _ in ma["chain"]] == [k for k, _ in mb["chain"]]
        assert all(np.array_equal(x, y) for (_, x), (_, y) in zip(ma["chain"], mb["chain"]))
        assert np.array_equal(ma["moving"], mb["moving"])


POSES = [pose((0.05 * k, 0, 0.02 * k), (0, 0.5 * k, 0)) for k in range(4)]


@pytest.fixture(scope="module")
def room() -> Room:
    return Room(0)


@pytest.fixture(scope="module")
def walk_b(room):
    """Robot r0's frames walked by a backbone with a fresh encoder and nothing run before."""
    from cerpe.backbones.config import OfflineConfig
    from cerpe.backbones.offline import OfflineGeometryBackbone
    from cerpe.backbones.xfeat import XFeatEncoder

    views = _frames(room, "r0", POSES)
    return views, _walk(OfflineGeometryBackbone(encoder=XFeatEncoder(OfflineConfig().keypoints)), views)


def test_memo_carries_the_motion_chain_and_the_moving_pixels(walk_b):
    views, outs = walk_b
    assert all(o.valid.all() and o.metric_unit for o in outs), [o.reasons for o in outs]
    m1, m2, m3 = (o.memos[0] for o in outs)
    assert all(o.memos[1:] == [None] * (len(o.memos) - 1) for o in outs)
    assert [k for k, _ in m1["chain"]] == [("r0", 0)]
    assert [k for k, _ in m3["chain"]] == [("r0", 2), ("r0", 1), ("r0", 0)]
    assert m3["chain"][1:] == m2["chain"] and m2["chain"][1:] == m1["chain"]  # older hops handed on unchanged
    for t, memo in ((1, m1), (2, m2), (3, m3)):
        T_t_prev = G.se3_inverse(POSES[t]) @ POSES[t - 1]
        assert np.linalg.norm(memo["chain"][0][1][:3, 3] - T_t_prev[:3, 3]) < 0.01
        # the object (its own motion) is what the chosen motion did not explain
        mask = grid_mask_image(memo["moving"], (K.height, K.width), 4)  # lone grid pixels dropped
        x0 = 40 + 24 * t
        assert mask[70:150, x0 + 10:x0 + 110].mean() > 0.5
        assert mask[:50].mean() < 0.05 and mask[170:].mean() < 0.05
    with pytest.raises(ValueError, match="read-only"):
        m3["chain"][0][1][0, 0] = 2.0  # read-only: a stored memo cannot change under the robot
    assert m3["moving"].flags.writeable is False


def test_chain_reaches_views_no_longer_in_the_pass(walk_b, monkeypatch):
    """Frame 1 is gone (not a keyframe): the chain of frame 2 still places frame 0 for the vote."""
    from cerpe.backbones.config import OfflineConfig
    from cerpe.backbones.offline import Pass, vote
    from cerpe.backbones.offline.vote import chained_views

    views, outs = walk_b
    m2 = outs[1].memos[0]
    p = Pass(views=[views[3], dataclasses.replace(views[2], memo=m2), views[0]], feats=[], Ks=[], cams=[],
             low_tex=[False] * 3, conf=OfflineConfig(), matcher=None, memos=[None, m2, None])
    (k, T_2_0), = chained_views(p, 1)
    assert k == 2
    assert np.array_equal(T_2_0, m2["chain"][0][1] @ m2["chain"][1][1])
    T_gt = G.se3_inverse(POSES[2]) @ POSES[0]
    assert np.linalg.norm(T_2_0[:3, 3] - T_gt[:3, 3]) < 0.01
    monkeypatch.setattr(vote, "VOTE_CHAIN_HOPS", 1)
    assert chained_views(p, 1) == []


def test_chain_length_is_bounded_by_vote_chain_hops(room, monkeypatch):
    from cerpe.backbones.offline import OfflineGeometryBackbone, context

    monkeypatch.setattr(context, "VOTE_CHAIN_HOPS", 2)
    outs = _walk(OfflineGeometryBackbone(), _frames(room, "h", POSES))
    assert [len(o.memos[0]["chain"]) for o in outs] == [1, 2, 2]


def test_a_pass_depends_on_its_views_alone(room, walk_b):
    """Robot r0's passes give the same bits after another encounter that used the same view keys
    with other pixels, another robot, and matches cached in the other order -- and when resumed
    from the memos alone by a new backbone."""
    from cerpe.backbones.offline import OfflineGeometryBackbone

    views, ref = walk_b
    busy = OfflineGeometryBackbone()
    other_poses = [pose((-0.04 * k, 0, 0.03 * k), (0, -1.0 * k, 0)) for k in range(4)]
    # the same keys with other pixels, walked backwards: ("r0", 0) placed on ("r0", 1) and so on
    _walk(busy, _frames(Room(3), "r0", other_poses, patch_seed=4)[::-1])
    _walk(busy, _frames(room, "r1", other_poses))  # another robot in the same room
    busy.infer([views[2], views[3]])  # the pair (3, 2) matched in the other order first
    for a, b in zip(ref, _walk(busy, views)):
        _assert_same(a, b)
    # resumed: a new backbone gets frame 3's pass with the memos the robot kept
    older = [dataclasses.replace(views[k], memo=ref[k - 1].memos[0] if k else None) for k in (2, 1, 0)]
    _assert_same(ref[-1], OfflineGeometryBackbone().infer([views[3]] + older))


def test_a_foreign_memo_is_refused(walk_b):
    from cerpe.backbones.offline import OfflineBackboneError, OfflineGeometryBackbone

    views, outs = walk_b
    bb = OfflineGeometryBackbone()
    with pytest.raises(OfflineBackboneError, match="another image"):  # frame 2's memo on frame 1
        bb.infer([views[3], dataclasses.replace(views[1], memo=outs[1].memos[0])])
    with pytest.raises(OfflineBackboneError, match="not this backbone's"):
        bb.infer([views[3], dataclasses.replace(views[2], memo={"motion": np.eye(4)})])
    # no prior placement (a single view, or an image-only pass): no memo
    assert bb.infer([views[0]]).memos == [None]
    no_depth = [dataclasses.replace(v, depth_m=None) for v in (views[1], views[0])]
    assert bb.infer(no_depth).memos == [None, None]


def test_views_not_wanted_are_left_out_of_a_metric_pass(room, walk_b):
    """Keyframes sent with ``pose_wanted`` False come back unplaced (``not-wanted``), except the
    reference. The current view, the reference and the memo are the bits of the full pass. A pass
    anchored on the current view's own prior places every view: the caller reads them."""
    from cerpe.backbones.offline import OfflineGeometryBackbone

    views, ref = walk_b
    older = [dataclasses.replace(views[k], memo=ref[k - 1].memos[0] if k else None) for k in (2, 1, 0)]
    full = ref[-1]
    out = OfflineGeometryBackbone().infer([views[3]] + [dataclasses.replace(v, pose_wanted=False) for v in older])
    r = full.reference
    assert r is not None and out.reference == r and out.metric_unit
    assert out.valid.tolist() == [s in (0, r) for s in range(4)]
    assert [out.reasons[s] for s in range(1, 4) if s != r] == ["not-wanted"] * 2
    assert np.array_equal(out.T_frame_cam[[0, r]], full.T_frame_cam[[0, r]])
    m, mf = out.memos[0], full.memos[0]
    assert all(np.array_equal(x, y) for (_, x), (_, y) in zip(m["chain"], mf["chain"]))
    assert np.array_equal(m["moving"], mf["moving"])
    # only the current view has a prior: it anchors the pass, and the others are placed on its points
    bare = [dataclasses.replace(v, depth_m=None, memo=None, pose_wanted=False) for v in (views[2], views[1])]
    out = OfflineGeometryBackbone().infer([views[3]] + bare)
    assert out.metric_unit and out.reference is None and out.valid.all(), out.reasons


def test_anchor_candidates_are_ranked_by_an_estimate_and_the_best_two_by_full_matches(room):
    """The depth-prior views a pass may anchor on: all ranked by their matches among the best keypoints
    (no full match), the first two of those by their full matches (two full matches, whatever the count);
    with two candidates or fewer, by full matches alone, as a full ranking would."""
    from cerpe.backbones.config import OfflineConfig
    from cerpe.backbones.offline import OfflineGeometryBackbone, Pass
    from cerpe.backbones.offline.context import RANK_FULL
    from cerpe.backbones.offline.matching import pinhole_camera

    views = _frames(room, "r0", POSES)[::-1]  # the current frame, then the older ones newest first
    bb = OfflineGeometryBackbone(OfflineConfig())
    feats = [bb.encoder.encode(v) for v in views]
    p = Pass(views=views, feats=feats, Ks=[K.K] * 4, cams=[pinhole_camera(K)] * 4, low_tex=[False] * 4,
             conf=bb.conf, matcher=bb.matcher)
    est = {d: p.shared_estimate(0, d) for d in (1, 2, 3)}
    assert bb.matcher.n_computed == 0 and all(n > 0 for n in est.values())
    ranked = p.rank_by_shared(0, [1, 2, 3])
    assert bb.matcher.n_computed == RANK_FULL == 2
    by_est = sorted((1, 2, 3), key=lambda d: -est[d])
    assert sorted(ranked[:2]) == sorted(by_est[:2]) and ranked[2] == by_est[2]
    assert len(p.m(0, ranked[0])) >= len(p.m(0, ranked[1]))
    full = {d: len(p.m(0, d)) for d in (1, 2, 3)}
    assert p.rank_by_shared(0, [2, 1]) == sorted([2, 1], key=lambda d: -full[d])

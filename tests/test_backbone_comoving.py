"""An object moving with the camera (a vehicle driving ahead) and the moving mask
(cerpe/backbones/offline/vote.py ``moving_pixels``): when the vote picks the object's motion
(standing still), the static scene is what that motion does not explain; pixels a motion that
lost a close vote explains (here the camera's true forward motion) must stay out of the mask,
or they stop voting and the wrong motion stays locked in while the object is in view."""
from __future__ import annotations

import numpy as np
import pytest
from test_backbone_offline import K, Room, _blocks, pose

from cerpe import geometry as G
from cerpe.protocols import View


@pytest.fixture(scope="module")
def room() -> Room:
    return Room(0)


def comoving_pass(room: Room, conf: dict | None = None):
    """Frame 1 (current) and frame 0 (its prior) of a camera moving 0.3 m forward, with an
    object 2 m ahead that keeps its place in the image (it moves with the camera)."""
    from cerpe.backbones.offline import OfflineGeometryBackbone
    from cerpe.backbones.offline.context import Pass
    from cerpe.backbones.offline.matching import pinhole_camera

    bb = OfflineGeometryBackbone(conf or {})
    Tw = [pose((0, 0, 0)), pose((0, 0, 0.3))]
    patch = _blocks(5, (110, 150), 6)
    views = []
    for k, T in enumerate(Tw):
        img, d = room.render(T)
        img, d = img.copy(), d.copy()
        img[70:180, 85:235] = patch
        d[70:180, 85:235] = 2.0
        views.append(View(("o", 1 - k), img, K, depth_m=d))
    views = views[::-1]  # [frame 1, frame 0]
    feats = [bb.encoder.encode(v) for v in views]
    p = Pass(views=views, feats=feats, Ks=[K.K, K.K], cams=[pinhole_camera(K)] * 2, low_tex=[False, False],
             conf=bb.conf, matcher=bb.matcher, memos=[None, None])
    T_true = G.se3_inverse(Tw[0]) @ Tw[1]  # frame-1 points into frame 0
    return p, T_true


def test_pixels_a_close_rival_explains_stay_out_of_the_moving_mask(room):
    from cerpe.backbones.offline.vote import consistency, moving_pixels

    p, T_true = comoving_pass(room)
    still = np.eye(4)
    inside, consistent = consistency(p, 0, 1, [still, T_true])
    assert consistent[0].sum() > 0 and consistent[1].sum() > 0
    alone = moving_pixels(p, 1, still)  # no rival: the room that moved is masked
    retested = moving_pixels(p, 1, still, [T_true])
    assert alone is not None and retested is not None
    room_px = inside[1] & consistent[1] & ~consistent[0]  # the room as the true motion explains it
    assert alone[room_px].mean() > 0.9
    assert retested[room_px].sum() == 0 and p.counts["moving-mask-retested"] == 1
    # what the true motion does not explain either (the object, the floor leaving the view) stays masked
    assert np.array_equal(retested, alone & ~consistent[1])

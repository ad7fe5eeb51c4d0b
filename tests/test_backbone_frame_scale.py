"""The offline backbone's running per-frame depth scale (:mod:`cerpe.backbones.offline.framescale`):
a monocular prior 8 % off in one frame is measured against the previous frame, carried in the memo,
and corrected before the next pass places a collaborator on it; a depth sensor's prior (its source
reports ``rel_sigma`` 0) leaves every pass bit for bit as it was."""
from __future__ import annotations

import numpy as np
import pytest

from cerpe import geometry as G
from cerpe.protocols import View
from test_backbone_offline import K, Room, pose
from test_backbone_offline_memo import _assert_same

MONO = 0.094  # a monocular prior's rel_sigma (mono-sim's)
POSES = {"A": pose((0, 0, 0)), "B": pose((0.05, 0, 0.1), (0, 1, 0)), "C": pose((0.1, 0, 0.2), (0, 2, 0)),
         "Q": pose((0.6, 0, 0.5), (0, -4, 0))}  # A, B, C: one robot's frames; Q: a collaborator 0.6 m aside


@pytest.fixture(scope="module")
def frames() -> dict[str, tuple[np.ndarray, np.ndarray]]:
    room = Room(0)
    return {n: room.render(T) for n, T in POSES.items()}


def _view(frames, name: str, factor: float = 1.0, rel: float | None = MONO, **kw) -> View:
    img, d = frames[name]
    return View(("r", name), img, K, depth_m=(d * factor).astype(np.float32), depth_rel_sigma=rel, **kw)


def _t(out, k: int, cur: str, other: str) -> tuple[float, float]:
    """View ``k``'s translation error (m) and estimated / true length."""
    gt = (G.se3_inverse(POSES[cur]) @ POSES[other])[:3, 3]
    t = out.T_frame_cam[k][:3, 3]
    return float(np.linalg.norm(t - gt)), float(np.linalg.norm(t) / np.linalg.norm(gt))


def _passes(frames, frame_scale: bool = True, rel: float | None = MONO, memo_scale=None):
    """Pass 1: B (prior x1.08) on A (exact). Pass 2: C (exact) on B (prior x1.08, with pass 1's
    memo, its log scale replaced by ``memo_scale`` when given) and the collaborator Q (no depth)."""
    from cerpe.backbones.config import OfflineConfig
    from cerpe.backbones.offline import OfflineGeometryBackbone

    bb = OfflineGeometryBackbone(OfflineConfig(frame_scale=frame_scale))
    o1 = bb.infer([_view(frames, "B", 1.08, rel, role="current"), _view(frames, "A", rel=rel, role="previous")])
    memo = o1.memos[0] if memo_scale is None else dict(o1.memos[0], log_scale=memo_scale)
    q = View(("q", "Q"), frames["Q"][0], K, role="collaborator")
    o2 = bb.infer([_view(frames, "C", rel=rel, role="current"),
                   _view(frames, "B", 1.08, rel, role="previous", memo=memo), q])
    return o1, o2


def test_a_scaled_prior_is_measured_against_the_previous_frame(frames):
    """B's prior 8 % long against A's exact one: its memo says log 1.08 (and the running mean
    ``FRAME_SCALE_RATE`` of it), and the ego-motion is as good as without the correction."""
    o1, _ = _passes(frames)
    a, m = o1.memos[0]["log_scale"]
    assert a == pytest.approx(np.log(1.08), abs=0.005)
    from cerpe.backbones.offline.framescale import FRAME_SCALE_RATE

    assert m == pytest.approx(FRAME_SCALE_RATE * a)
    assert _t(o1, 1, "B", "A")[0] < 0.002


def test_the_direct_estimate_is_placed_on_the_corrected_scale(frames):
    """B's memo says its prior is 8 % above the robot's running mean (log scale (log 1.08, 0)):
    the next pass brings it back, so B's translation and the collaborator Q's (placed on B's
    and C's points) come out at their true length; uncorrected, both are 4-8 % long."""
    _, on = _passes(frames, memo_scale=(float(np.log(1.08)), 0.0))
    _, off = _passes(frames, frame_scale=False)
    err_on, len_on = _t(on, 2, "C", "Q")
    err_off, len_off = _t(off, 2, "C", "Q")
    assert on.valid[2] and off.valid[2]
    assert abs(len_on - 1) < 0.01 < 0.04 < abs(len_off - 1)
    assert err_on < 0.5 * err_off
    assert abs(_t(on, 1, "C", "B")[1] - 1) < 0.01 < 0.05 < abs(_t(off, 1, "C", "B")[1] - 1)
    assert on.memos[0]["log_scale"][0] == pytest.approx(0.0, abs=0.005)  # C: on the running mean


@pytest.mark.parametrize("rel", [0.0, 0.01, None])
def test_a_depth_sensor_prior_is_left_alone(frames, rel):
    """A prior whose source reports no scale noise (a depth sensor's 0, a dataset's 1 %, or none
    said): the same bits as with the correction off, and no scale in the memo."""
    a = _passes(frames, rel=rel)
    b = _passes(frames, frame_scale=False, rel=rel)
    for x, y in zip(a, b):
        _assert_same(x, y)
        assert x.memos[0]["log_scale"] is None


def test_reference_mean_and_correction_without_memos():
    from cerpe.backbones.offline import framescale

    img = np.zeros((4, 4, 3), np.uint8)
    d = np.full((4, 4), 2.0, np.float32)
    views = [View("c", img, K, d, role="current"), View("k", img, K, d, role="keyframe"),
             View("p", img, K, d, role="previous")]
    assert framescale.reference_mean(views, [None, None, None]) == 0.0
    memos = [None, {"log_scale": (0.1, 0.05)}, {"log_scale": (0.2, 0.15)}]
    assert framescale.reference_mean(views, memos) == 0.15  # the previous frame's mean first
    out = framescale.correct_views(views, memos, 0.15)
    assert out[0] is views[0]
    assert np.allclose(out[1].depth_m, 2.0 * np.exp(0.05)) and np.allclose(out[2].depth_m, 2.0 * np.exp(-0.05))

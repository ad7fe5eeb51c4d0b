"""Algorithm 1 end to end with the ground-truth test doubles (tests/gt_backbone.py).

The GT backbone answers every pass in a new random frame with a new unknown
scale, so exact answers here mean: one pass per robot per step, scale recovered
per pass, odometry composed only from within-pass differences, anchors and
propagation in the right frames.
"""
from __future__ import annotations

import time
from collections import Counter

import numpy as np
import pytest

from cerpe.algorithm import AlgorithmConfig, Team, run_encounter
from cerpe.geometry import e_pos, e_rot
from cerpe.messages import DescriptorMessage
from cerpe.records import STAGES
from cerpe.transport import Channel
from gt_backbone import GTBackbone, OverlapDescriptor, SensorDepthDouble, World, make_world

CFG = AlgorithmConfig().override({"scale.min_pixels": 20})  # 32x24 test images: ~30 % of pixels see a point


def run(world: World, config: AlgorithmConfig = CFG, channel: Channel | None = None, backbone=None, depth=None,
        descriptor=None):
    backbone = backbone or GTBackbone(world, seed=1)
    team = Team(world.robot_ids, descriptor or OverlapDescriptor(world), backbone,
                depth or SensorDepthDouble(), config, channel)
    return team, backbone, list(team.run_encounter(world.to_encounter()))


def pair_errors(world: World, results) -> list[tuple]:
    out = []
    for res in results:
        for p in res.pairs:
            i, j = world.index(p.ego), world.index(p.other)
            if p.T_cj_ci is None:
                out.append((res.step, p.ego, p.other, p.source, np.nan, np.nan))
                continue
            gt = world.gt_T_cj_ci(res.step, i, j)
            out.append((res.step, p.ego, p.other, p.source, float(e_pos(p.T_cj_ci[:3, 3], gt[:3, 3])),
                        float(e_rot(p.T_cj_ci, gt))))
    return out


def expected_sources(windows: list[tuple[int, int]], n_steps: int, propagate: bool = True) -> list[str]:
    src, anchored = [], False
    for t in range(n_steps):
        if any(lo <= t < hi for lo, hi in windows):
            src.append("direct")
            anchored = True
        else:
            src.append("propagated" if anchored and propagate else "none")
    return src


@pytest.mark.parametrize("track_previous", [True, False])
def test_two_robots_exact_with_gt_backbone(track_previous):
    world = make_world(2, 40, seed=1)
    team, bb, results = run(world, AlgorithmConfig().override({"scale.min_pixels": 20, "odometry.track_previous": track_previous}))
    errs = pair_errors(world, results)
    want = expected_sources([(5, 10), (25, 30)], 40)
    for step, ego, other, source, ep, er in errs:
        assert source == want[step], (step, ego, other)
        if source != "none":
            assert ep < 1e-5 and er < 1e-6, (step, ego, other, ep, er)
    # success after the first anchor is 100 %
    after = [e for e in errs if e[0] >= 5]
    assert all(e[3] != "none" for e in after)
    for res in results:
        for p in res.pairs:
            assert p.anchor_step == (p.step if p.source == "direct" else (-1 if p.source == "none"
                                                                         else (9 if p.step < 25 else 29)))
            if p.source == "none":
                assert p.reason == "no-anchor"
        # odometry = ground truth relative to each robot's first frame, although
        # every pass used another frame and unit
        for k, r in enumerate(res.robots):
            np.testing.assert_allclose(r.T_odom_cam, world.gt_odometry(k, res.step), atol=1e-5)
    # exactly one joint pass per robot per step: [current] + memory newest first (+ the previous
    # frame when tracking and it is not the newest keyframe) + collaborator
    assert len(bb.calls) == 2 * 40
    kf_steps: dict[str, list[int]] = {"r0": [], "r1": []}
    calls = iter(bb.calls)
    for res in results:
        for r in res.robots:
            keys = next(calls)
            other = "r1" if r.robot == "r0" else "r0"
            collab = [(other, res.step, "jpeg")] if want[res.step] == "direct" else []
            prev = ([(r.robot, res.step - 1)] if track_previous and res.step > 0
                    and kf_steps[r.robot][-1] != res.step - 1 else [])
            assert keys == [(r.robot, res.step)] + [(r.robot, s) for s in reversed(kf_steps[r.robot])] + prev + collab
            if r.keyframe:
                kf_steps[r.robot] = (kf_steps[r.robot] + [res.step])[-5:]
            assert r.n_keyframes == len(kf_steps[r.robot])
    assert all(1 <= len(v) <= 5 for v in kf_steps.values())



@pytest.mark.parametrize("trust", [True, False])
def test_backbone_metric_unit_skips_the_scale_step_only_when_configured(trust):
    """A backbone that says its pass is in metres (metric_unit) but is off by 2x: with
    backbone_metric_unit the algorithm takes s = 1 (and inherits the error), without it
    METHOD.md step 4 recovers s = 0.5 and the odometry is exact."""
    world = make_world(2, 12, seed=3)
    bb = GTBackbone(world, unit_range=(2.0, 2.0), claim_metric=True, seed=1)
    _, _, results = run(world, AlgorithmConfig().override({"scale.min_pixels": 20, "scale.metric_unit": trust}), backbone=bb)
    last = results[-1].robots[0]
    scales = {r.scale for res in results[1:] for r in res.robots}
    moved = np.linalg.norm(world.gt_odometry(0, results[-1].step)[:3, 3])
    got = np.linalg.norm(last.T_odom_cam[:3, 3])
    assert moved > 0.1
    if trust:
        assert scales == {1.0}
        assert got == pytest.approx(2 * moved, rel=1e-6)
    else:
        assert np.allclose(sorted(scales), 0.5, atol=1e-9)
        np.testing.assert_allclose(last.T_odom_cam, world.gt_odometry(0, results[-1].step), atol=1e-6)

def test_bytes_and_records():
    world = make_world(2, 12, seed=2)
    team, _, results = run(world)
    desc_bytes = DescriptorMessage.wire_bytes(team.descriptor.dim, "fp16")
    for res in results:
        gate = 5 <= res.step < 10
        for r in res.robots:
            assert r.bytes_sent["descriptor"] == desc_bytes and r.bytes_sent["pose"] == 70
            assert r.bytes_sent.get("request", 0) == (16 if gate else 0)
            assert (r.bytes_sent.get("reply", 0) > 34) == gate
            assert set(r.timings_s) <= set(STAGES) and r.timings_s["backbone"] > 0
            assert r.degradations == [] and np.isfinite(r.scale)
            row = r.as_row()
            assert row["bytes_total"] == r.bytes_total
        for p in res.pairs:
            other = next(r for r in res.robots if r.robot == p.other)
            ego = next(r for r in res.robots if r.robot == p.ego)
            assert p.bytes_pair == ego.bytes_sent.get("request", 0) + other.bytes_sent.get("reply", 0)
            assert p.gate_open == gate and p.gate_score == pytest.approx(0.6 if gate else 0.05, abs=2e-3)


@pytest.mark.parametrize("sensor", [True, False])
def test_a_sensors_depth_is_timed_apart_inside_scale(sensor):
    """A depth source that says its depth comes with the frame (``sensor``): the step times reading it as
    the ``sensor`` part of ``scale``, which ``cerpe bench`` leaves out of the robot's work; a depth
    network's time (no ``sensor``) is the robot's and has no such part."""
    class Slow(SensorDepthDouble):
        def depth_m(self, view, frame):
            time.sleep(0.002)
            return super().depth_m(view, frame)

    depth = Slow()
    if sensor:
        depth.sensor = True
    world = make_world(2, 4, seed=2)
    _, _, results = run(world, depth=depth)
    for res in results:
        for r in res.robots:
            part = r.parts_s.get("sensor", 0.0)
            assert (part >= 0.002) == sensor and part <= r.timings_s["scale"]


def test_three_robots_pair_specific_windows():
    windows = {(0, 1): [(3, 8)], (0, 2): [(12, 16)], (1, 2): [(20, 24), (30, 33)]}
    world = make_world(3, 40, seed=3, windows=windows)
    team, bb, results = run(world)
    assert len(bb.calls) == 3 * 40
    for step, ego, other, source, ep, er in pair_errors(world, results):
        i, j = sorted((int(ego[1]), int(other[1])))
        assert source == expected_sources(windows[(i, j)], 40)[step], (step, ego, other)
        if source != "none":
            assert ep < 1e-5 and er < 1e-6, (step, ego, other, ep, er)
    for res in results:
        for k, r in enumerate(res.robots):
            np.testing.assert_allclose(r.T_odom_cam, world.gt_odometry(k, res.step), atol=1e-5)


def test_without_em_gives_none_when_gate_closed():
    world = make_world(2, 40, seed=1)
    _, _, results = run(world, AlgorithmConfig().override({"scale.min_pixels": 20, "backend.propagate": False}))
    want = expected_sources([(5, 10), (25, 30)], 40, propagate=False)
    for step, ego, other, source, ep, er in pair_errors(world, results):
        assert source == want[step]
        if source == "direct":
            assert ep < 1e-5 and er < 1e-6
    assert {p.reason for r in results for p in r.pairs if p.source == "none"} == {"gate-closed"}


def test_error_grows_smoothly_with_depth_bias():
    """Per-frame depth bias (which the median cannot remove) plus per-pixel noise
    and 5 % outliers: translation error grows with the bias, rotation stays exact."""
    world = make_world(2, 40, seed=4)
    mean_pos, max_rot = [], []
    sigmas = [0.0, 0.02, 0.05, 0.1, 0.2]
    for sigma in sigmas:
        depth = SensorDepthDouble(bias_sigma=sigma, pixel_sigma=0.1, outlier_frac=0.05, seed=9)
        _, _, results = run(world, depth=depth)
        errs = np.array([(e[4], e[5]) for e in pair_errors(world, results) if e[3] != "none"])
        assert errs.size and np.all(np.isfinite(errs))
        mean_pos.append(errs[:, 0].mean())
        max_rot.append(errs[:, 1].max())
    assert np.all(np.diff(mean_pos) > 0), mean_pos
    assert mean_pos[0] < 0.05  # pixel noise + outliers alone: nearly exact
    assert max(max_rot) < 1e-6
    # roughly linear in sigma (no blow-up): error per unit of bias within a factor 3
    slopes = (np.array(mean_pos[1:]) - mean_pos[0]) / np.array(sigmas[1:])
    assert slopes.max() / slopes.min() < 3, slopes


@pytest.mark.parametrize("verify", [False, True])
def test_lossy_channel_run_completes_with_counted_degradations(verify):
    world = make_world(3, 40, seed=5, windows={(0, 1): [(3, 8), (20, 26)], (0, 2): [(10, 15)],
                                               (1, 2): [(10, 15), (30, 35)]})
    ch = Channel(p_drop=0.1, p_garble=0.1, seed=3)
    team, _, results = run(world, AlgorithmConfig().override({"scale.min_pixels": 20, "anchors.verify": verify}), channel=ch)
    degr = Counter(d for res in results for r in res.robots for d in r.degradations)
    assert degr["msg:lost"] == ch.counts["msg:lost"] > 0
    assert degr["msg:garbled"] == ch.counts["msg:garbled"] > 0
    errs = pair_errors(world, results)
    est = [e for e in errs if e[3] != "none"]
    # a direct estimate needs four frames through (descriptor, request, reply, pose): with 20 % of
    # frames lost, verification (three agreeing estimates) comes late in the short windows
    assert len(est) > (0.3 if verify else 0.5) * len(errs)
    assert all(np.isfinite(e[4]) and np.isfinite(e[5]) for e in est)
    missing_desc = [p for res in results for p in res.pairs if np.isnan(p.gate_score)]
    assert missing_desc and all(not p.gate_open for p in missing_desc)
    assert all(p.reason.startswith("descriptor-missing") for p in missing_desc)
    # a stale pose of the other robot is used and flagged, never silently
    stale = [p for res in results for p in res.pairs if "stale-pose" in p.reason]
    assert degr["pose:stale"] == len(stale)


def test_ego_no_estimate_keeps_last_pose_then_recovers():
    world = make_world(2, 30, seed=6)
    bb = GTBackbone(world, seed=1, invalid_keys=[("r0", t) for t in (12, 13, 14)])
    _, _, results = run(world, backbone=bb)
    X = {res.step: res.robots[0].T_odom_cam for res in results}
    for t in (12, 13, 14):
        assert "ego:no-estimate" in results[t].robots[0].degradations
        np.testing.assert_array_equal(X[t], X[11])
        assert not results[t].robots[0].keyframe
    for t in (11, 15, 20, 29):  # keyframes carry correct poses: odometry recovers exactly
        np.testing.assert_allclose(X[t], world.gt_odometry(0, t), atol=1e-5)


def test_memory_reinit_when_no_keyframe_can_be_placed():
    world = make_world(2, 30, seed=7)
    # from step 20 on, r0's passes cannot place any of its frames older than step 20
    bb = GTBackbone(world, seed=1, invalid=lambda cur, key: cur[0] == "r0" and cur[1] >= 20
                    and key[0] == "r0" and key[1] < 20)
    _, _, results = run(world, backbone=bb)
    r20 = results[20].robots[0]
    assert "ego:no-estimate" in r20.degradations and "memory:reinit" in r20.degradations
    assert r20.keyframe and r20.n_keyframes == 1
    X19, X20 = results[19].robots[0].T_odom_cam, r20.T_odom_cam
    np.testing.assert_array_equal(X20, X19)  # constant-position across the gap
    for t in (21, 25, 29):  # then odometry continues from the re-initialised keyframe
        rel = np.linalg.inv(world.gt_odometry(0, 20)) @ world.gt_odometry(0, t)
        np.testing.assert_allclose(results[t].robots[0].T_odom_cam, X20 @ rel, atol=1e-5)


def test_scale_fallback_to_last_valid():
    world = make_world(2, 40, seed=8)
    bb = GTBackbone(world, unit_range=(2.0, 2.0), seed=1)  # constant unit: the last scale stays right
    depth = SensorDepthDouble(none_keys=[("r0", t) for t in range(1, 40)])
    _, _, results = run(world, backbone=bb, depth=depth)
    degr = Counter(d for res in results for d in res.robots[0].degradations)
    assert degr["scale:fallback-last"] > 0 and degr["scale:skipped-no-metric-depth"] > 0
    assert Counter(d for res in results for d in res.robots[1].degradations) == Counter()
    for res in results:
        assert res.robots[0].scale == pytest.approx(0.5)
        np.testing.assert_allclose(res.robots[0].T_odom_cam, world.gt_odometry(0, res.step), atol=1e-5)


def test_no_scale_ever_gives_no_direct_estimate_but_no_crash():
    world = make_world(2, 15, seed=9)
    depth = SensorDepthDouble(none_keys=[("r0", t) for t in range(15)])
    _, _, results = run(world, depth=depth)
    for res in results:
        r0 = res.robots[0]
        assert np.isnan(r0.scale) and "scale:unavailable" in r0.degradations
        np.testing.assert_array_equal(r0.T_odom_cam, np.eye(4))
        p = next(p for p in res.pairs if p.ego == "r0")
        assert p.source == "none"
        if 5 <= res.step < 10:
            assert p.reason == "no-scale; no-anchor"
        q = next(p for p in res.pairs if p.ego == "r1")
        assert q.source != "none" or res.step < 5  # r1 has scale and anchors normally


def test_blank_frame_closes_gate_and_is_counted():
    world = make_world(2, 20, seed=1)
    desc = OverlapDescriptor(world, zero_keys=[("r0", 7)])
    _, _, results = run(world, descriptor=desc)
    r0, r1 = results[7].robots
    assert "descriptor:zero-norm" in r0.degradations and not r0.keyframe
    assert "descriptor:other-zero-norm" in r1.degradations
    for p in results[7].pairs:
        assert not p.gate_open and np.isnan(p.gate_score)
        assert p.source == "propagated" and p.anchor_step == 6
    assert [p.reason for p in results[7].pairs] == ["own-descriptor-degenerate; unverified",
                                                    "other-descriptor-degenerate; unverified"]
    for res in results[8:]:
        assert all(p.source != "none" for p in res.pairs)


def test_thresholds_precedence_explicit_over_descriptor_over_paper():
    world = make_world(2, 12, seed=1)
    strict = OverlapDescriptor(world, thresholds={"tau": 0.7, "tau_m": 0.95, "tau_k": 0.1})
    team = Team(world.robot_ids, strict, GTBackbone(world), SensorDepthDouble(), CFG)
    assert (team.config.gate.tau, team.config.memory.tau_m, team.config.memory.tau_k) == (0.7, 0.95, 0.1)
    assert team.agents[0].memory.conf.tau_m == 0.95
    assert all(p.source == "none" for res in team.run_encounter(world.to_encounter()) for p in res.pairs)
    team = Team(world.robot_ids, strict, GTBackbone(world), SensorDepthDouble(),
                AlgorithmConfig().override({"gate.tau": 0.5, "scale.min_pixels": 20}))
    assert team.config.gate.tau == 0.5 and team.config.memory.tau_m == 0.95
    assert any(p.source == "direct" for res in team.run_encounter(world.to_encounter()) for p in res.pairs)
    plain = Team(world.robot_ids, OverlapDescriptor(world), GTBackbone(world), SensorDepthDouble())
    assert (plain.config.gate.tau, plain.config.memory.tau_m, plain.config.memory.tau_k) == (0.2, 0.9, 0.2)


def test_module_level_run_encounter_and_rerun_resets():
    world = make_world(2, 10, seed=1)
    enc = world.to_encounter()
    a = list(run_encounter(enc, OverlapDescriptor(world), GTBackbone(world, seed=1), SensorDepthDouble(), CFG))
    team = Team(world.robot_ids, OverlapDescriptor(world), GTBackbone(world, seed=5), SensorDepthDouble(), CFG)
    list(team.run_encounter(enc))
    b = list(team.run_encounter(enc))  # second walk starts from scratch
    for ra, rb in zip(a, b):
        for pa, pb in zip(ra.pairs, rb.pairs):
            assert pa.source == pb.source
        np.testing.assert_allclose(ra.robots[0].T_odom_cam, rb.robots[0].T_odom_cam, atol=1e-6)


class _ReferenceBackbone(GTBackbone):
    """Exact pose for the current view and its oldest own keyframe (the ``reference``);
    every other own view of the pass 30 cm off."""

    def infer(self, views):
        out = super().infer(views)
        own = [s for s in range(1, len(views)) if views[s].key[0] == views[0].key[0] and len(views[s].key) == 2]
        if own:
            out.reference = min(own, key=lambda s: views[s].key[1])  # the oldest keyframe
            for s in own:
                if s != out.reference and out.valid[s]:
                    out.T_frame_cam[s][:3, 3] += 0.3 * np.linalg.norm(out.T_frame_cam[s][:3, 3]) + 0.3
        return out


class _LazyBackbone(GTBackbone):
    """A metric pass that leaves the own views the agent does not want (``View.pose_wanted``) unplaced,
    but for the reference: the newest own view besides the current one."""

    def __init__(self, world, **kw):
        super().__init__(world, unit_range=(1.0, 1.0), claim_metric=True, **kw)
        self.wanted: list[tuple[bool, list[bool]]] = []  # per pass: collaborators in it, pose_wanted per view

    def infer(self, views):
        out = super().infer(views)
        self.wanted.append((any(v.role == "collaborator" for v in views), [v.pose_wanted for v in views]))
        own = [s for s in range(1, len(views)) if views[s].role in ("keyframe", "previous")]
        if own:
            out.reference = max(own, key=lambda s: views[s].key[1])
        for s in own:
            if s != out.reference and not views[s].pose_wanted:
                out.T_frame_cam[s], out.valid[s], out.reasons[s] = np.nan, False, "not-wanted"
        return out


@pytest.mark.parametrize("metric_unit", [True, False])
def test_the_agent_asks_for_the_poses_it_reads(metric_unit):
    """Without collaborators in the pass only the current view's pose is wanted (the reference's is
    read, whatever it is); with collaborators, or when a metric pass is scaled anyway
    (``scale.metric_unit`` off), every pose is. A backbone that skips the others loses nothing."""
    world = make_world(2, 25, seed=4)
    bb = _LazyBackbone(world)
    cfg = AlgorithmConfig().override({"scale.min_pixels": 20, "scale.metric_unit": metric_unit})
    _, _, results = run(world, cfg, backbone=bb)
    collab = [w for c, w in bb.wanted if c]
    lean = [w for c, w in bb.wanted if not c and len(w) > 1]
    assert collab and lean
    assert all(all(w) for w in collab)
    assert all(w == [True] + [not metric_unit] * (len(w) - 1) for w in lean)
    for res in results:
        for k, r in enumerate(res.robots):
            np.testing.assert_allclose(r.T_odom_cam, world.gt_odometry(k, res.step), atol=1e-5)


def test_ego_motion_chains_through_the_backbones_reference_view():
    """The pass's reference view (what the backbone measured the current view against) is
    used for the odometry even when the previous frame and newer keyframes are placed too."""
    world = make_world(2, 25, seed=4)
    bb = _ReferenceBackbone(world)
    team, _, results = run(world, AlgorithmConfig().override({"scale.min_pixels": 20, "odometry.track_previous": True}), backbone=bb)
    assert any(len(c) > 3 for c in bb.calls)  # passes with several own views did happen
    for res in results:
        for k, r in enumerate(res.robots):
            np.testing.assert_allclose(r.T_odom_cam, world.gt_odometry(k, res.step), atol=1e-5)

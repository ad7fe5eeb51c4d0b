"""Message loss (issue 21 item 4): what a robot does about each lost frame, `cerpe run --loss`, the sweep step."""
from __future__ import annotations

import dataclasses

import numpy as np
import pandas as pd
import pytest

from cerpe.algorithm import AlgorithmConfig, Team
from cerpe.algorithm.bridge import PoseLog
from cerpe.atomicio import read_json
from cerpe.geometry import e_rot, interpolate_pose, random_se3
from cerpe.messages import ImageReply, PoseMessage, decode
from cerpe.pipeline import cerpe_method, message_loss
from cerpe.pipeline import run as rp
from cerpe.scene import Setting
from cerpe.transport import Channel, LossSpec, TransportError
from gt_backbone import GTBackbone, OverlapDescriptor, SensorDepthDouble, make_world


class _Drop(Channel):
    """A channel that drops exactly the frames ``drop(sender, receiver, message)`` names."""

    def __init__(self, robots, drop):
        super().__init__(robots)
        self.drop = drop

    def _deliver(self, sender, frame, receiver):
        if self.drop(sender, receiver, decode(frame)):
            self._inbox[receiver].append((sender, None))
        else:
            super()._deliver(sender, frame, receiver)


def _team(world, channel=None, **messages):
    """A team of the ground-truth doubles; ``messages``: knobs of the ``messages`` group."""
    sets = {"scale.min_pixels": 20, **{f"messages.{k}": v for k, v in messages.items()}}
    return Team(world.robot_ids, OverlapDescriptor(world), GTBackbone(world, seed=1), SensorDepthDouble(),
                AlgorithmConfig().override(sets), channel)


def _pairs(results, ego="r0", other="r1"):
    return {res.step: next(p for p in res.pairs if p.ego == ego and p.other == other) for res in results}


def test_pose_log_interpolates_between_and_extrapolates_after():
    rng = np.random.default_rng(0)
    A, B = random_se3(rng), random_se3(rng)
    log = PoseLog()
    assert log.bridged(3) is None
    log.note(2, A)
    assert np.allclose(log.bridged(3), A)  # one pose: held
    log.note(4, B)
    assert np.allclose(log.bridged(3), interpolate_pose(A, B, 0.5))
    assert np.allclose(log.bridged(6), interpolate_pose(A, B, 2.0))  # constant velocity on
    assert np.allclose(log.exact(4), B) and log.exact(3) is None

    @dataclasses.dataclass
    class Held:
        X_j: np.ndarray

    held = Held(B.copy())
    log.defer(5, held)
    assert log.note(5, A) == 0 and np.allclose(held.X_j, B)  # the step itself: not a later pose
    log2 = PoseLog()
    log2.note(4, A)
    log2.defer(5, held)
    assert log2.note(7, B) == 1 and np.allclose(held.X_j, interpolate_pose(A, B, 1 / 3))


def test_reply_carries_the_pose_its_sender_had(monkeypatch):
    from cerpe.algorithm.agent import RobotAgent

    world = make_world(2, 8, seed=3, windows={(0, 1): [(0, 8)]})
    got = []
    orig = RobotAgent.accept_reply

    def spy(self, other, reply):
        if self.robot_id == "r0":
            got.append((reply.step, reply.pose_step, reply.T_odom_cam))
        return orig(self, other, reply)

    monkeypatch.setattr(RobotAgent, "accept_reply", spy)
    recs = list(_team(world).run_encounter(world.to_encounter()))
    X1 = {res.step: r.T_odom_cam for res in recs for r in res.robots if r.robot == "r1"}
    assert got and got[0][:2] == (0, 0) and np.allclose(got[0][2], np.eye(4))  # first step: identity, exact
    for step, pose_step, X in got[1:]:  # in process the owner answers before its pass: its previous pose
        assert pose_step == step - 1 and np.allclose(X, X1[step - 1])


def test_reply_whose_pose_message_is_lost_still_anchors():
    world = make_world(2, 24, seed=5, windows={(0, 1): [(3, 6)]})
    lossless = _pairs(_team(world).run_encounter(world.to_encounter()))
    # every pose message r1 sends r0 during the overlap window is lost; replies and descriptors arrive
    lossy_ch = _Drop(world.robot_ids, lambda s, r, m: isinstance(m, PoseMessage) and (s, r) == ("r1", "r0")
                     and 3 <= m.step < 6)
    results = list(_team(world, lossy_ch).run_encounter(world.to_encounter()))
    lossy = _pairs(results)
    degr = [d for res in results for r in res.robots if r.robot == "r0" for d in r.degradations]
    window = [lossy[t] for t in range(3, 6)]
    assert all(p.source == "direct" for p in window)
    assert not any("anchor-not-stored" in p.reason for p in window)  # before version 2: no anchor at all
    assert {p.anchor_verdict for p in window} & {"accepted", "verified"}
    assert degr.count("pose:bridged") == 3 and degr.count("pose:bridged-next") == 3
    after = [t for t in range(6, 24) if lossless[t].source == "propagated"]
    assert after and all(lossy[t].source == "propagated" and 3 <= lossy[t].anchor_step < 6 for t in after)
    # the bridged anchor is corrected from the next pose: its propagation stays close to the lossless one
    gt = world.to_encounter()
    for t in after:
        T_gt = gt.gt_T_cj_ci(t, 0, 1)
        assert e_rot(lossy[t].T_cj_ci, T_gt) < e_rot(lossless[t].T_cj_ci, T_gt) + 0.02
        assert np.linalg.norm(lossy[t].T_cj_ci[:3, 3] - T_gt[:3, 3]) < \
            np.linalg.norm(lossless[t].T_cj_ci[:3, 3] - T_gt[:3, 3]) + 0.1


def _lose_descriptors_and_a_request(steps: set[int], request_step: int):
    """r0 never hears r1's descriptors of ``steps``; r0's image request of ``request_step`` is lost."""
    return lambda s, r, m: (((s, r) == ("r1", "r0") and type(m).__name__ == "DescriptorMessage" and m.step in steps)
                            or ((s, r) == ("r0", "r1") and type(m).__name__ == "ImageRequest"
                                and m.step == request_step))


def test_lost_descriptor_defers_the_gate_and_lost_reply_keeps_the_anchor():
    world = make_world(2, 14, seed=7, windows={(0, 1): [(2, 10)]})
    ch = _Drop(world.robot_ids, _lose_descriptors_and_a_request({5}, 7))
    results = list(_team(world, ch, stale_descriptor_steps=0).run_encounter(world.to_encounter()))
    pairs = _pairs(results)
    degr = {res.step: [d for r in res.robots if r.robot == "r0" for d in r.degradations] for res in results}
    assert not pairs[5].gate_open and "descriptor-missing" in pairs[5].reason and "descriptor:missing" in degr[5]
    assert pairs[5].source == "propagated"  # the anchor of the steps before is carried
    assert pairs[7].gate_open and "msg:reply-missing" in degr[7] and pairs[7].source == "propagated"
    assert pairs[6].source == pairs[8].source == "direct"  # the gate works again the step after


def test_a_lost_descriptor_is_replaced_by_the_previous_one_at_most_max_age_old():
    world = make_world(2, 14, seed=7, windows={(0, 1): [(2, 12)]})
    ch = _Drop(world.robot_ids, _lose_descriptors_and_a_request({5, 8, 9}, -1))
    results = list(_team(world, ch).run_encounter(world.to_encounter()))  # stale_descriptor_steps=1 (default)
    pairs = _pairs(results)
    degr = {res.step: [d for r in res.robots if r.robot == "r0" for d in r.degradations] for res in results}
    # step 5: step 4's descriptor opens the gate; the image of step 5 is requested and placed
    assert pairs[5].gate_open and pairs[5].source == "direct"
    assert "descriptor:missing" in degr[5] and "descriptor:stale-used" in degr[5]
    # steps 8, 9 lost in a row: 8 uses step 7's; at 9 the last fresh one (7) is 2 steps old: closed
    assert pairs[8].gate_open and "descriptor:stale-used" in degr[8]
    assert not pairs[9].gate_open and "descriptor-missing" in pairs[9].reason
    assert "descriptor:stale-used" not in degr[9] and pairs[9].source == "propagated"


def test_a_lost_reply_is_asked_for_again_within_the_step():
    world = make_world(2, 8, seed=7, windows={(0, 1): [(0, 8)]})
    dropped = []

    def first_reply_of_step_5(s, r, m):  # only the first copy: the retry's reply arrives
        if isinstance(m, ImageReply) and (s, r) == ("r1", "r0") and m.step == 5 and not dropped:
            dropped.append(m)
            return True
        return False

    results = list(_team(world, _Drop(world.robot_ids, first_reply_of_step_5)).run_encounter(world.to_encounter()))
    pairs = _pairs(results)
    degr = [d for r in results[5].robots if r.robot == "r0" for d in r.degradations]
    assert dropped and pairs[5].source == "direct" and "msg:reply-missing" not in degr
    assert degr.count("msg:request-retried") == 1
    assert pairs[5].bytes_pair == 2 * 16 + len(dropped[0].encode())  # two requests, the reply that came
    r1_sent = next(r for r in results[5].robots if r.robot == "r1").bytes_sent["reply"]
    assert r1_sent == 2 * len(dropped[0].encode())  # the owner answered both
    no_retry = list(_team(world, _Drop(world.robot_ids, lambda s, r, m: isinstance(m, ImageReply) and m.step == 5
                                       and (s, r) == ("r1", "r0")), request_retries=0)
                    .run_encounter(world.to_encounter()))
    assert _pairs(no_retry)[5].source == "propagated"


def test_a_reply_lost_twice_comes_with_the_second_retry():
    """The default asks twice more within the step (request_retries=2): a pair without an anchor
    whose reply is lost has no other way to get one that step."""
    world = make_world(2, 8, seed=7, windows={(0, 1): [(0, 8)]})

    def drop(limit):
        dropped = []

        def first_replies_of_step_5(s, r, m):
            if isinstance(m, ImageReply) and (s, r) == ("r1", "r0") and m.step == 5 and len(dropped) < limit:
                dropped.append(m)
                return True
            return False
        return first_replies_of_step_5

    results = list(_team(world, _Drop(world.robot_ids, drop(2))).run_encounter(world.to_encounter()))
    degr = [d for r in results[5].robots if r.robot == "r0" for d in r.degradations]
    assert _pairs(results)[5].source == "direct" and degr.count("msg:request-retried") == 2
    once = list(_team(world, _Drop(world.robot_ids, drop(2)), request_retries=1).run_encounter(world.to_encounter()))
    degr = [d for r in once[5].robots if r.robot == "r0" for d in r.degradations]
    assert _pairs(once)[5].source == "propagated" and "msg:reply-missing" in degr


def test_garbled_frames_are_counted_never_raised():
    world = make_world(3, 10, seed=2, windows={(0, 1): [(0, 10)], (0, 2): [(0, 10)], (1, 2): [(0, 10)]})
    results = list(_team(world, Channel(p_garble=1.0, seed=3)).run_encounter(world.to_encounter()))
    degr = [d for res in results for r in res.robots for d in r.degradations]
    assert degr.count("msg:garbled") > 0 and degr.count("descriptor:missing") == 3 * 2 * 10
    assert all(p.source == "none" and not p.gate_open for res in results for p in res.pairs)
    half = list(_team(world, Channel(p_drop=0.2, p_garble=0.3, seed=3)).run_encounter(world.to_encounter()))
    assert any(p.source != "none" for res in half for p in res.pairs)
    assert {"msg:garbled", "msg:lost"} <= {d for res in half for r in res.robots for d in r.degradations}


def test_loss_spec_checks_and_seeds_per_encounter():
    with pytest.raises(TransportError, match="--loss"):
        LossSpec(1.5)
    with pytest.raises(TransportError, match="--loss-seed"):
        LossSpec(0.1, 0.0, -1)
    spec = LossSpec(0.5, 0.0, 3)
    draws = lambda ch: [ch._rng.random() for _ in range(5)]
    assert draws(spec.channel(["a"], "enc0")) == draws(spec.channel(["a"], "enc0"))
    assert draws(spec.channel(["a"], "enc0")) != draws(spec.channel(["a"], "enc1"))
    assert LossSpec().as_dict() == {"loss": 0.0, "garble": 0.0, "loss_seed": None}


# --------------------------------------------------------------------------- cerpe run --loss, the sweep
def _world_setting():
    world = make_world(3, 18, seed=4, windows={(0, 1): [(2, 12)], (0, 2): [(4, 14)], (1, 2): [(6, 16)]})
    enc = world.to_encounter("gt")
    enc.overlap = np.full((world.n_steps, 3, 3), 0.5)
    return world, Setting("synthetic-indoor", [enc], metric_depth="sensor")


@pytest.fixture()
def gt_plugins(monkeypatch):
    """The real ``run`` path (prepare_method, the per-encounter lossy channel) over the ground-truth doubles."""
    world, setting = _world_setting()

    def plugins_and_config(method, metric_depth, depth_options=None, preset="paper", sets=None):
        assert not sets, "the ground-truth doubles take no --set here"
        from cerpe import knobs
        from cerpe.method_config import METHOD_OVERRIDES

        cfg = AlgorithmConfig().override({"scale.min_pixels": 20, **METHOD_OVERRIDES[method]})
        plugins = type("P", (), {"descriptor": OverlapDescriptor(world), "backbone": GTBackbone(world, seed=1),
                                 "depth": SensorDepthDouble()})
        return plugins, cfg, {"tree": knobs.as_dict(cfg), "preset": preset}

    monkeypatch.setattr(cerpe_method, "cerpe_plugins_and_config", plugins_and_config)
    return setting


def _table(path):
    df = pd.read_csv(path)
    return df[[c for c in df.columns if not (c.startswith("t_") and c.endswith("_s"))]]  # wall times differ


def test_loss_option_reproduces_the_run_for_a_seed(tmp_path, gt_plugins):
    m = tmp_path / "toy.yaml"
    m.write_text("name: synthetic-indoor\n")
    run = lambda out, spec: rp.run_method(m, "cerpe", tmp_path / out, setting=gt_plugins, progress=False, loss=spec)
    a, b = run("a", LossSpec(0.3, 0.1, 5)), run("b", LossSpec(0.3, 0.1, 5))
    c = run("c", LossSpec(0.3, 0.1, 6))
    for f in ("steps.csv", "robots.csv"):
        pd.testing.assert_frame_equal(_table(a / "gt" / f), _table(b / "gt" / f))
    assert not _table(a / "gt" / "robots.csv").equals(_table(c / "gt" / "robots.csv"))
    meta = read_json(a / "run.json", "run.json")
    assert meta["channel"] == {"loss": 0.3, "garble": 0.1, "loss_seed": 5}
    assert meta["config"]["method_config"]["channel"] == meta["channel"]
    assert meta["label"] == "CERPE (loss 30%, garble 10%, seed 5)"  # what cerpe eval lists for the run
    with pytest.raises(rp.RunError, match="another configuration"):  # resume knows the loss it ran with
        run("a", LossSpec(0.3, 0.1, 6))
    lossless = run("d", None)
    assert "msg:lost" not in open(lossless / "gt" / "robots.csv").read()
    assert "msg:lost" in open(a / "gt" / "robots.csv").read()
    with pytest.raises(rp.RunError, match="exchanges no messages"):
        rp.prepare_method("sift-ransac", 0, channel=LossSpec(0.1))


def test_sweep_step_on_a_tiny_fixture(tmp_path, gt_plugins, monkeypatch):
    m = tmp_path / "toy.yaml"
    m.write_text("name: synthetic-indoor\n")
    conf = {"losses": [0.0, 0.3, 0.5], "loss_seeds": [1, 2]}
    paths = {"manifest": m, "runs": tmp_path / "sweep"}
    out = message_loss.main(conf, paths, setting=gt_plugins)
    S = pd.read_csv(out)
    assert sorted(zip(S["method"], S["loss"])) == [(mm, p) for mm in ("cerpe", "cerpe-wo-em") for p in (0, .3, .5)]
    base = S[(S["method"] == "cerpe") & (S["loss"] == 0)].iloc[0]
    assert base["msg:lost"] == 0 and base["success_after_covis_vs_lossless"] == pytest.approx(1.0)
    lossy = S[(S["method"] == "cerpe") & (S["loss"] == 0.5)].iloc[0]
    assert lossy["msg:lost"] > 0 and lossy["success_pct"] < base["success_pct"]
    wo = S[(S["method"] == "cerpe-wo-em") & (S["loss"] == 0.5)].iloc[0]
    assert wo["success_pct"] <= lossy["success_pct"]
    assert set(message_loss.check(S)) == {"success_ratio", "e_rot_ratio", "passed"}
    assert "| cerpe | 30 % |" in message_loss.markdown(S)
    # cached: a second call runs nothing
    monkeypatch.setattr(rp, "run_methods", lambda *a, **k: pytest.fail("ran again"))
    assert message_loss.main(conf, paths, setting=gt_plugins) == out


def test_sweep_reuses_the_lossless_run_on_its_first_steps(tmp_path, gt_plugins):
    m = tmp_path / "toy.yaml"
    m.write_text("name: synthetic-indoor\n")
    full = {meth: rp.run_method(m, meth, tmp_path / "full" / meth, setting=gt_plugins, progress=False)
            for meth in ("cerpe", "cerpe-wo-em")}
    conf = {"losses": [0.0, 0.3], "max_steps": 12}
    S = pd.read_csv(message_loss.main(conf, {"manifest": m, "runs": tmp_path / "sweep", "lossless": full},
                                      setting=gt_plugins))
    assert not any((tmp_path / "sweep").glob("*loss00*"))  # the lossless point is read, not run again
    assert (S["steps"] == 12).all() and S.groupby("loss")["n_frames"].nunique().eq(1).all()
    # the same frames at every loss (the lossless run cut to 12 steps), once per loss seed when lossy
    n_seeds = len(message_loss.default_conf["loss_seeds"])
    n = S.set_index(["method", "loss"])["n_frames"]
    assert (n.xs(0.3, level="loss") == n_seeds * n.xs(0.0, level="loss")).all()

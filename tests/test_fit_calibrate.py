"""Threshold calibration on development data: the tau rule, recall at precision, pair samples (known answers),
and `cerpe fit thresholds` end to end on fixture-sized development suites."""
from __future__ import annotations

import numpy as np
import pytest

from cerpe.geometry import make_se3
from cerpe.fit.calibrate import (consecutive_similarity, cross_scene_negatives, largest_tau_with_recall,
                                 pair_samples, recall_at_precision, set_figures)
from cerpe.scene import CameraIntrinsics, Encounter, RobotStream


def test_recall_at_precision_known_answer():
    s = np.array([0.9, 0.8, 0.7, 0.6, 0.5, 0.4])
    y = np.array([1, 1, 0, 1, 0, 1], bool)
    # thresholds: 0.9 P1 R.25, 0.8 P1 R.5, 0.7 P.67, 0.6 P.75 R.75, 0.5 P.6, 0.4 P.67 R1
    assert recall_at_precision(s, y, 0.8) == pytest.approx(0.5)
    assert recall_at_precision(s, y, 0.7) == pytest.approx(0.75)
    assert recall_at_precision(s, y, 0.6) == pytest.approx(1.0)
    assert recall_at_precision(np.array([0.1, 0.9]), np.array([1, 0], bool), 0.8) == 0.0
    assert np.isnan(recall_at_precision(s, np.zeros(6, bool)))
    # tied scores are one threshold: both or neither
    assert recall_at_precision(np.array([0.5, 0.5]), np.array([1, 0], bool), 0.8) == 0.0


def test_largest_tau_with_recall_on_every_set():
    sets = {"a": (np.array([0.9, 0.8, 0.7, 0.6, 0.1]), np.array([1, 1, 1, 1, 0], bool)),  # 4 pos: 4th best 0.6 (R 1)
            "b": (np.array([0.55, 0.45, 0.35, 0.3, 0.2, 0.9]), np.array([1, 1, 1, 1, 1, 0], bool))}  # 5 pos: 4th 0.3
    tau = largest_tau_with_recall(sets, 0.8)
    assert tau == pytest.approx(0.3)
    for s, y in sets.values():
        assert np.mean(s[y] >= tau) >= 0.8
    # rounding goes down, so the recall holds after it
    assert largest_tau_with_recall({"c": (np.array([0.123456]), np.array([True]))}, 0.8) == pytest.approx(0.1234)
    # a set without positives does not constrain tau; none at all is an error
    assert largest_tau_with_recall({**sets, "n": (np.array([0.99]), np.array([False]))}, 0.8) == pytest.approx(0.3)
    with pytest.raises(ValueError):
        largest_tau_with_recall({"n": (np.array([0.99]), np.array([False]))})


def test_set_figures_and_targets():
    s = np.array([0.95, 0.9, 0.85, 0.8, 0.3, 0.2, 0.1, 0.86])
    y = np.array([1, 1, 1, 1, 0, 0, 0, 0], bool)
    f = set_figures(s, y, tau=0.5)
    assert f["n_positive"] == 4 and f["n_negative"] == 4
    assert f["roc_auc"] == pytest.approx(14 / 16)  # 0.86 beats two positives
    assert f["precision"] == pytest.approx(4 / 5) and f["recall"] == 1.0 and f["recall_at_p80"] == 1.0
    assert not f["auc_target_met"] and f["pr_target_met"]
    only_pos = set_figures(s[y], y[y], tau=0.5)
    assert np.isnan(only_pos["roc_auc"]) and not only_pos["auc_target_met"]


def test_cross_scene_negatives_and_consecutive_similarity():
    rng = np.random.default_rng(0)
    D1 = rng.normal(size=(2, 4, 8))
    D2 = rng.normal(size=(1, 6, 8))
    neg = cross_scene_negatives(D1, [D2], stride=2)
    assert neg.shape == (2 * 2 * 1 * 3,)
    assert neg[0] == pytest.approx(D1[0, 0] @ D2[0, 0])
    c = consecutive_similarity(D1)
    assert c.shape == (2 * 3,) and c[0] == pytest.approx(D1[0, 1] @ D1[0, 0])


def _wall_encounter() -> Encounter:
    """Two robots facing a wall 2 m ahead; robot b turns away (180 deg) from step 2 on."""
    K = CameraIntrinsics(50.0, 50.0, 15.5, 11.5, 32, 24)
    depth = np.full((24, 32), 2.0, np.float32)
    away = np.diag([-1.0, 1.0, -1.0])  # 180 deg about y
    Ta = np.stack([make_se3(np.eye(3), [0.0, 0, 0])] * 4)
    Tb = np.stack([make_se3(np.eye(3), [0.1, 0, 0])] * 2 + [make_se3(away, [0.1, 0, 0])] * 2)
    imgs = [np.zeros((24, 32, 3), np.uint8)] * 4
    robots = [RobotStream("a", K, np.arange(4) * 0.1, imgs, Ta, depth=[depth] * 4, depth_units_per_m=1.0),
              RobotStream("b", K, np.arange(4) * 0.1, imgs, Tb, depth=[depth] * 4, depth_units_per_m=1.0)]
    ov = np.ones((4, 2, 2))
    ov[2:, 0, 1] = ov[2:, 1, 0] = 0.0
    return Encounter("wall", robots, overlap=ov)


def test_pair_samples_label_same_and_any_step():
    enc = _wall_encounter()
    D = np.zeros((2, 4, 3), np.float32)
    D[0, :, 0] = 1.0
    D[1, :2, 0] = 1.0
    D[1, 2:, 1] = 1.0  # b's descriptor changes when it turns away
    same = pair_samples(enc, D, any_step=False, progress=False)
    assert list(same["label"]) == [1.0, 1.0, 0.0, 0.0] and list(same["score"]) == [1.0, 1.0, 0.0, 0.0]
    anyp = pair_samples(enc, D, any_step=True, progress=False)
    assert len(anyp) == 16
    lab = anyp.set_index(["t", "u"])["label"]
    assert lab[(0, 1)] == 1.0 and lab[(3, 0)] == 1.0 and lab[(0, 2)] == 0.0 and lab[(3, 3)] == 0.0
    assert np.all(anyp["score"].to_numpy() == (anyp["u"] < 2).to_numpy(float))
    assert len(pair_samples(enc, D, stride=2, any_step=True, progress=False)) == 4


def test_fit_thresholds_on_the_fixture_suite(tmp_path, capsys):
    """`cerpe fit thresholds` end to end on fixture-sized development suites (seed 2), without real data;
    the paper seed is one error line."""
    import json

    from cerpe.cli import main

    argv = ["fit", "thresholds", "--synth-preset", "fixture", "--dev-out", str(tmp_path / "dev"), "--real",
            "--out", str(tmp_path / "th.json"), "--samples", str(tmp_path / "samples.csv")]
    assert main(argv + ["--synth-seeds", "0"]) == 2
    err = capsys.readouterr().err
    assert "paper-default" in err and len(err.strip().splitlines()) == 1 and "Traceback" not in err
    assert main(argv + ["--synth-seeds", "2"]) == 0
    out = capsys.readouterr().out
    res = json.loads((tmp_path / "th.json").read_text())
    th = res["thresholds"]
    assert 0 < th["tau_k"] <= th["tau_m"] < 1 and -1 < th["tau"] < 1
    assert res["provenance"]["synthetic"]["seeds"] == [2] and res["provenance"]["real"] == {}
    assert res["provenance"]["command"].startswith("cerpe ")
    names = set(res["figures"])
    assert names == {"dev-fixture-synthetic-cad-s2", "dev-fixture-synthetic-indoor-s2"}
    for f in res["figures"].values():  # the rule: recall >= 0.8 on every set with positives
        after = f["any_step"]["after"]
        assert after["n_positive"] == 0 or after["recall"] >= 0.8
    assert "tau" in out and "R@P80" in out and (tmp_path / "samples.csv").is_file()
    # --dry-run prints and writes nothing
    (tmp_path / "th.json").unlink()
    assert main(argv + ["--synth-seeds", "2", "--dry-run"]) == 0
    assert not (tmp_path / "th.json").exists()


def test_descriptor_cache_is_reused_only_for_the_same_descriptor(tmp_path):
    """describe_setting's cache: the same descriptor reads it back; another setting or another
    subtracted mean describes anew (a stale cache would score the gate with old descriptors)."""
    from types import SimpleNamespace

    from cerpe.fit.descriptor_codecs import describe_setting

    class Desc:
        def __init__(self, conf, mean):
            self.conf, self.descriptor_mean, self.dim, self.calls = conf, mean, 4, 0

        def describe(self, view):
            self.calls += 1
            return np.full(4, view.key[1] + self.conf["b"], np.float32)

    robot = SimpleNamespace(robot_id="r0", intrinsics=np.eye(3), image=lambda t: np.zeros((8, 8, 3), np.uint8))
    setting = SimpleNamespace(encounters=[SimpleNamespace(name="e0", robots=[robot], n_steps=3)])
    cache = tmp_path / "c.npz"
    a = Desc({"b": 1.0}, np.zeros(4, np.float32))
    first = describe_setting(a, setting, cache, progress=False)
    again = Desc({"b": 1.0}, np.zeros(4, np.float32))
    assert np.array_equal(describe_setting(again, setting, cache, progress=False)[0], first[0]) and again.calls == 0
    other_conf = Desc({"b": 2.0}, np.zeros(4, np.float32))
    assert describe_setting(other_conf, setting, cache, progress=False)[0][0, 0, 0] == 2.0 and other_conf.calls == 3
    other_mean = Desc({"b": 2.0}, np.ones(4, np.float32))
    describe_setting(other_mean, setting, cache, progress=False)
    assert other_mean.calls == 3

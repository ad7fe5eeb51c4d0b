"""Every development study in lab/ runs, on the tiny fixture suite: `cerpe dev --synth fixture` runs of
the indoor world (seed 2) and, for the studies that render their own development suites, the fixture
sizes in place of the development ones. Smoke tests: the plumbing and the printed tables, not the figures
(the pose graph's fit and replay have known-answer tests in tests/test_lab_graph.py)."""
from __future__ import annotations

import argparse
import importlib
import io
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from cerpe.pipeline import dev

STUDIES = ("anchor_replay", "descriptor_codec_auc", "ego_replay", "graph_calibrate", "graph_replay", "matchers",
           "policy", "render_examples", "reply_codecs", "scale", "wide_pairs")
SET = "dev-fixture-synthetic-indoor-s2"
ROOT = Path(__file__).resolve().parents[1]


def _study(monkeypatch, capsys, name: str, *argv) -> str:
    """Run ``python -m lab.NAME ARGV`` in this process; its stdout."""
    mod = importlib.import_module(f"lab.{name}")
    monkeypatch.setattr(sys, "argv", [f"lab.{name}", *map(str, argv)])
    assert mod.main() in (None, 0)
    return capsys.readouterr().out


@pytest.fixture(scope="module")
def runs(tmp_path_factory) -> Path:
    """`cerpe dev --synth fixture --seeds 2` on the indoor world: cerpe, cerpe-wo-em and cerpe-graph runs."""
    out = tmp_path_factory.mktemp("lab") / "dev"
    res = dev.dev_report(out, seeds=[2], methods=("cerpe", "cerpe-wo-em", "cerpe-graph"), synth="fixture",
                         real=False, sets=[f"{SET[:-3]}*"], progress=False, echo=lambda s: None)
    assert res["errors"] == []
    return out


@pytest.fixture()
def fixture_sized(monkeypatch):
    """The studies that render development suites get the fixture's sizes (seconds, not minutes)."""
    full = dev.synthetic_set
    monkeypatch.setattr(dev, "synthetic_set", lambda setting, seed, sizes, out, progress=True:
                        full(setting, seed, "fixture", out, progress))


@pytest.mark.parametrize("name", STUDIES)
def test_every_study_says_what_it_measures(name, monkeypatch, capsys):
    with pytest.raises(SystemExit) as exc:
        _study(monkeypatch, capsys, name, "--help")
    assert exc.value.code == 0 and "usage:" in capsys.readouterr().out


def test_matchers(runs, monkeypatch, capsys):
    from lab import matchers, sets

    manifest = runs / "manifests" / f"{SET}.yaml"
    # its own process: the study's tables print to the sys.stdout of the time it was imported
    res = subprocess.run([sys.executable, "-m", "lab.matchers", "--sets", "--synth", str(manifest), "--matchers",
                          "xfeat-mnn", "--max-cases", "1"], cwd=ROOT, capture_output=True, text=True, timeout=300)
    assert res.returncode == 0 and "collaborator vs ego current frame" in res.stdout, res.stderr[-2000:]
    # the study's own cases start at step 15, after the fixture's 12 frames: its core on earlier steps
    cases = sets.synthetic(manifest, step_every=6, first_step=4, memory=1, gap=2)[:2]
    args = argparse.Namespace(min_inliers=25, min_ratio=0.2, pnp_px=3.0, epipolar_px=1.0)
    cache = matchers.FeatureCache()
    rows = [matchers.register(m, cache, c, v, args) for m in matchers.build_matchers(["xfeat-mnn", "xfeat-lg"])
            for c in cases for v in range(len(c.ego))]
    assert len(rows) == 2 * sum(len(c.ego) for c in cases) and all(r.n_matches >= r.n_inliers >= 0 for r in rows)
    text = io.StringIO()
    matchers.print_table(SET, [r for r in rows if r.view == 0], {}, [25, 50], out=text)
    matchers.memory_table(SET, rows, [25], out=text)
    assert "| xfeat-lg |" in text.getvalue() and "current >=25" in text.getvalue()


def test_scale(runs, monkeypatch, capsys):
    out = _study(monkeypatch, capsys, "scale", "--synth", runs / "manifests" / f"{SET}.yaml", "--data", "none",
                 "--methods", "gt-vs-depth", "keypoint_depths", "backbone")
    assert out.count("| manifests r0") == 9 and "barrel k1=-0.2 not undone | backbone |" in out
    out = _study(monkeypatch, capsys, "scale", "--runs", runs)
    assert f"| {SET} |" in out


def test_wide_pairs(runs, tmp_path, monkeypatch, capsys):
    out = _study(monkeypatch, capsys, "wide_pairs", "--set", "synth", "--suite",
                 runs / "synth" / "fixture" / "indoor-team-seed2", "--methods", "sift-ransac", "--every", 3,
                 "--min-deg", 10, "--max-deg", 170, "--out", tmp_path)
    assert "pairs (10-170 deg)" in out and "sift-ransac" in out and "all" in out


def test_anchor_replay(runs, tmp_path, monkeypatch, capsys):
    run = runs / "runs" / SET / "cerpe"
    rec = tmp_path / "unchecked"
    out = _study(monkeypatch, capsys, "anchor_replay", "--record", runs / "manifests" / f"{SET}.yaml", rec)
    assert f"run folder: {rec}" in out
    steps = pd.read_csv(next(rec.glob("*/steps.csv")))
    assert set(steps["anchor_verdict"].dropna()) == {"unchecked"}  # every direct estimate is the anchor
    out = _study(monkeypatch, capsys, "anchor_replay", run, "--what", "both")
    assert "--- replay with" in out and "max_wrong_carried" in out
    out = _study(monkeypatch, capsys, "anchor_replay", run, "--what", "report", "--set",
                 "anchors.report_unverified=false")
    assert "carried_longest_steps" in out and SET in out
    with pytest.raises(SystemExit, match="unknown key 'anchors.rot_tol'"):
        _study(monkeypatch, capsys, "anchor_replay", run, "--set", "anchors.rot_tol=0.1")


def test_ego_replay(runs, monkeypatch, capsys):
    import cerpe.backbones.offline.reconstruction as rc

    monkeypatch.setattr(rc, "total_votes", rc.total_votes)  # --trace replaces it: restored after the test
    out = _study(monkeypatch, capsys, "ego_replay", runs / "manifests" / f"{SET}.yaml", "all", "r0", "--steps", 3,
                 "--trace")
    assert "t= 2 est" in out and out.splitlines()[-1].startswith("all: sum err")


def test_graph_replay(runs, monkeypatch, capsys):
    from cerpe.algorithm.graph import GRAPH_MODEL
    from lab.graphdev import run_graph_model

    assert run_graph_model(runs / "runs" / SET / "cerpe-graph") == GRAPH_MODEL  # the default tree's knobs
    out = _study(monkeypatch, capsys, "graph_replay", "--runs", runs / "runs", "--set", "kernel_k=1,2")
    lines = out.splitlines()
    assert lines[0].startswith("{'kernel_k': 1}: graph / min(CERPE, w/o EM) geo-mean") and "pass: e_pos" in lines[0]
    assert lines[2].startswith("{'kernel_k': 2}")


def test_graph_calibrate(runs, monkeypatch, capsys):
    """The fixture's runs hold a few direct estimates, fewer than a noise fit needs: the study says so;
    its odometry fit, replays and summaries run on them (the direct fit's known answer: test_lab_graph)."""
    from cerpe.algorithm.graph import GRAPH_MODEL
    from lab import graph_calibrate as gc

    with pytest.raises(SystemExit, match="nothing to fit"):
        _study(monkeypatch, capsys, "graph_calibrate", "--runs", runs / "runs", "--grid", "--oracle")
    sets = gc._sets(runs / "runs")
    assert [d.name for d in sets] == [SET] and len(gc.direct_table(sets)) > 0
    odo = gc.fit_odometry(sets)
    assert odo["n_steps"] > 0 and odo["odo_trans_per_step"] >= 0 and odo["growth"]
    g = gc.grid(sets, gc.scaled(GRAPH_MODEL, 1.0, 1.0, 1.0), [1.0, 2.0], [1.0], [1.0], [1.0])
    assert len(g) == 2 and np.isfinite(g["e_rot_rad"]).all()


def test_reply_codecs(runs, fixture_sized, tmp_path, monkeypatch, capsys):
    out = _study(monkeypatch, capsys, "reply_codecs", "--synth-seeds", 2, "--real", "--dev-out", runs, "--cases", 1,
                 "--settings", "jpeg:90:1", "webp-grey:75:0.5", "--csv", tmp_path / "cases.csv")
    assert "all sets: 2 cases" in out and "webp-grey:75:0.5" in out
    df = pd.read_csv(tmp_path / "cases.csv")
    assert len(df) == 4 and (df.groupby("setting")["bytes"].mean()["webp-grey:75:0.5"]
                             < df.groupby("setting")["bytes"].mean()["jpeg:90:1.0"])


def test_descriptor_codec_auc(runs, fixture_sized, tmp_path, monkeypatch, capsys):
    from cerpe.compress import default_projection_path, load_projection

    proj = tmp_path / "projection.npz"  # --write-tau writes into the file: a copy, never the shipped one
    shutil.copy(default_projection_path(), proj)
    out = _study(monkeypatch, capsys, "descriptor_codec_auc", "--synth-seeds", 2, "--real", "--dev-out", runs,
                 "--projection", proj, "--write-tau")
    assert "pca-pq - full" in out and f"wrote the thresholds into {proj}" in out
    assert set(load_projection(proj).thresholds) == {"pca-int8", "pca-pq"}


def test_policy(runs, fixture_sized, monkeypatch, capsys):
    out = _study(monkeypatch, capsys, "policy", "--seeds", 2, "--out", runs, "--sets", SET, "--schemes", "paper",
                 "always")
    assert f"### {SET}" in out and "always send" in out and "where the bytes go" in out
    assert set(pd.read_csv(runs / "policy.csv")["scheme"]) == {"paper", "always"}


def test_render_examples(tmp_path, monkeypatch, capsys):
    from lab import render_examples

    monkeypatch.setattr(render_examples, "ROWS", [render_examples.ROWS[0], render_examples.ROWS[4]])
    out = _study(monkeypatch, capsys, "render_examples", "--size", "64x48", "--frames", 8, "--out",
                 tmp_path / "examples.png")
    assert (tmp_path / "examples.png").stat().st_size > 1000 and "examples.png" in out


def test_policy_grid_builds_a_tree_per_entry():
    from cerpe import method_config
    from lab.policy import GRID

    trees = {name: method_config.build(preset, "cerpe", sets) for name, (preset, sets) in GRID.items()}
    assert trees["lean-pe-u2-rc-l1"] == trees["lean"]  # the preset, spelt out from LEAN_V1
    assert trees["lean-v1"].policy.miss_limit == 3 and trees["lean-v1"].policy.recheck_rot_rad == 0.0
    assert trees["gate-compressed"].policy.mode == "gate" and trees["gate-compressed"].messages.reply_codec == "webp"

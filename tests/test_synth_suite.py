"""Fixture suite on disk: manifest layout, file formats, overlap transitions, caching, errors."""
from __future__ import annotations

import json
import os
from pathlib import Path

import numpy as np
import pytest
import yaml

from cerpe.cli import main as cli_main
from cerpe.geometry import se3_from_tq_xyzw
from cerpe.scene import load_depth_m
from cerpe.synth import SynthError, generate_suite, generate_suites
from cerpe.synth.groundtruth import has_transition
from cerpe.synth.writer import SUITES, full_conf, plan_for


@pytest.fixture(scope="module")
def fixture_suite(tmp_path_factory) -> dict[str, Path]:
    return generate_suites("fixture", tmp_path_factory.mktemp("synth"), progress=False)


def test_manifest_follows_the_architecture_layout(fixture_suite):
    assert set(fixture_suite) == {"synthetic-cad", "synthetic-indoor"}
    for setting, manifest in fixture_suite.items():
        doc = yaml.safe_load(manifest.read_text())
        assert doc["name"] == setting and doc["adapter"] == "mocap" and doc["metric_depth"] == "sensor"
        assert doc["enabled"] is True and doc["data_root"] == "."
        root = manifest.parent / doc["data_root"]
        assert len(doc["encounters"]) == 1
        for enc in doc["encounters"]:
            ov = np.load(root / enc["overlap"])
            n = len(enc["robots"])
            assert ov.shape == (12, n, n)
            for r in enc["robots"]:
                assert r["trajectory_format"] == "tum" and r["T_body_cam"] == "identity"
                assert r["depth_units_per_m"] == 1000 and r["interpolate"] is False
                rgb = sorted((root / r["images"]).glob("*.png"))
                dep = sorted((root / r["depth"]).glob("*.png"))
                assert len(rgb) == 12 and [p.stem for p in rgb] == [p.stem for p in dep]
                cam = yaml.safe_load((root / r["intrinsics"]).read_text())
                assert (cam["width"], cam["height"]) == (160, 120)
                assert {"fx", "fy", "cx", "cy", "distortion"} <= set(cam)
                lines = [ln for ln in (root / r["trajectory"]).read_text().splitlines() if not ln.startswith("#")]
                assert len(lines) == 12 and all(len(ln.split()) == 8 for ln in lines)
                assert [f"{float(ln.split()[0]):.6f}" for ln in lines] == [p.stem for p in rgb]


def test_files_round_trip_to_the_plan(fixture_suite):
    manifest = fixture_suite["synthetic-indoor"]
    world, conf = SUITES["fixture"]["synthetic-indoor"]
    plan = plan_for(world, full_conf(world, conf), 0)
    doc = yaml.safe_load(manifest.read_text())
    r = doc["encounters"][0]["robots"][1]
    rows = np.loadtxt(manifest.parent / r["trajectory"])
    T = np.stack([se3_from_tq_xyzw(row[1:4], row[4:8]) for row in rows])
    np.testing.assert_allclose(T, plan.T_world_cam[1], atol=1e-6)
    # depth PNG (mm) reads back through the shared loader
    d = load_depth_m(sorted((manifest.parent / r["depth"]).glob("*.png"))[3], 1000)
    assert d.dtype == np.float32 and d.shape == (120, 160) and (d > 0).mean() > 0.9 and d.max() < 15.0
    meta = json.loads((manifest.parent / doc["encounters"][0]["name"] / "meta.json").read_text())
    va = np.array(meta["viewing_angle_rad"])
    assert va.shape == (12, 3, 3) and np.allclose(va, va.transpose(0, 2, 1), atol=1e-6)


def test_every_fixture_encounter_crosses_both_overlap_thresholds(fixture_suite):
    for manifest in fixture_suite.values():
        doc = yaml.safe_load(manifest.read_text())
        for enc in doc["encounters"]:
            ov = np.load(manifest.parent / enc["overlap"])
            assert has_transition(ov, 0.3, 0.05), (enc["name"], ov.max(0), ov.min(0))


def test_same_arguments_render_nothing_and_different_ones_need_force(fixture_suite):
    manifest = fixture_suite["synthetic-cad"]
    out = manifest.parent
    world, conf = SUITES["fixture"]["synthetic-cad"]
    png = next(out.rglob("*.png"))
    before = png.stat().st_mtime_ns
    assert generate_suite(world, out, conf, progress=False, setting="synthetic-cad") == manifest
    assert png.stat().st_mtime_ns == before
    with pytest.raises(SynthError, match="--force"):
        generate_suite(world, out, {**conf, "seed": 1}, progress=False)
    assert not any(p.name.endswith(".partial") for p in out.parent.iterdir())


def test_force_replaces_and_leaves_nothing_half_written(tmp_path):
    conf = {"seed": 2, "n_frames": 3, "fps": 2.0, "size": (48, 32), "n_robots": 2}
    m = generate_suite("indoor-team", tmp_path / "a", conf, progress=False)
    m2 = generate_suite("indoor-team", tmp_path / "a", {**conf, "seed": 3}, force=True, progress=False)
    assert m2 == m and json.loads((tmp_path / "a" / "meta.json").read_text())["key"]["args"]["seed"] == 3
    assert sorted(os.listdir(tmp_path)) == [".a.lock", "a"]  # the lock file stays (deleting it would race)


@pytest.mark.parametrize("world,conf,match", [
    ("moon-base", {}, "unknown world"),
    ("indoor-team", {"size": (8, 8)}, "size"),
    ("cad-intersection", {"n_frames": 1}, "n_frames"),
    ("cad-intersection", {"n_robots": 1}, "n_robots"),
    ("indoor-team", {"colour": "red"}, "unknown generator argument"),
])
def test_bad_arguments_raise(tmp_path, world, conf, match):
    with pytest.raises(SynthError, match=match):
        generate_suite(world, tmp_path / "x", conf, progress=False)


def test_not_a_synth_folder_is_refused(tmp_path):
    (tmp_path / "x").mkdir()
    (tmp_path / "x" / "precious.txt").write_text("keep me")
    for force in (False, True):
        with pytest.raises(SynthError, match="not a cerpe synth output"):
            generate_suite("indoor-team", tmp_path / "x", {"size": (48, 32), "n_frames": 2}, progress=False, force=force)
    assert (tmp_path / "x" / "precious.txt").exists()


def test_cli_prints_one_line_errors(tmp_path, capsys):
    rc = cli_main(["synth", "indoor-team", "--out", str(tmp_path / "o"), "--size", "8x8", "--no-progress"])
    err = capsys.readouterr().err
    assert rc == 2 and "size 8x8" in err and "Traceback" not in err


def test_cli_renders_a_tiny_world(tmp_path, capsys):
    rc = cli_main(["synth", "cad-intersection", "--out", str(tmp_path / "c"), "--size", "64x48", "--frames", "3",
                   "--fps", "2", "--seed", "5", "--no-progress"])
    assert rc == 0 and (tmp_path / "c" / "manifest.yaml").is_file()
    assert "synthetic-cad" in capsys.readouterr().out


def test_two_worker_processes_give_the_same_files_as_one(tmp_path):
    conf = {"seed": 1, "n_encounters": 2, "n_frames": 3, "fps": 2.0, "size": (48, 32), "n_robots": 2}
    one = generate_suite("cad-intersection", tmp_path / "one", {**conf, "workers": 1}, progress=False)
    two = generate_suite("cad-intersection", tmp_path / "two", {**conf, "workers": 2}, progress=False)
    files = sorted(p.relative_to(one.parent) for p in one.parent.rglob("*.png"))
    assert len(files) == 2 * 2 * 3 * 2
    for rel in files:
        assert (one.parent / rel).read_bytes() == (two.parent / rel).read_bytes()

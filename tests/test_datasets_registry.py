"""Registry, entry points, example (KITTI-style) adapter, synthetic adapter caching, `cerpe check`, committed manifests."""
from __future__ import annotations

import shutil
from pathlib import Path

import cv2
import numpy as np
import pytest
import yaml

import cerpe.datasets.registry as registry
from cerpe.cli import main as cerpe_main
from cerpe.datasets import (LoadReport, ManifestError, find_manifests, get_adapter, known_adapters, load_manifest,
                            load_setting, register_adapter)
from cerpe.datasets import synthetic as synthetic_mod
from cerpe.geometry import make_se3, se3_inverse, so3_exp
from cerpe.scene import Setting
from test_datasets_fixtures import write_mocap

REPO = Path(__file__).resolve().parents[1]


def test_unknown_adapter_lists_known_ones(tmp_path: Path) -> None:
    p = tmp_path / "m.yaml"
    p.write_text("name: x\nadapter: nope\nencounters: []\n")
    with pytest.raises(ManifestError, match="known adapters: .*mocap.*openmars") as info:
        load_manifest(p)
    assert info.value.problems[0].field == "adapter" and info.value.problems[0].file == str(p)
    assert {"mocap", "openmars", "synthetic", "example"} <= set(known_adapters())


class _ToyAdapter:
    """A third-party adapter: reuses mocap's loader under a different name."""

    name = "toy"
    top_level_fields = ("flavour",)

    def validate(self, manifest):
        return [] if manifest.raw.get("flavour") == "mint" else [manifest.problem("flavour", "must be mint")]

    def load(self, manifest, report):
        from cerpe.datasets.mocap import MocapAdapter

        return MocapAdapter().load(manifest, report)


def test_entry_point_adapter_is_found(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    class _EP:
        name = "toy"

        def load(self):
            return _ToyAdapter

    monkeypatch.setattr(registry, "entry_points", lambda group: [_EP()] if group == registry.ENTRY_POINT_GROUP else [])
    assert "toy" in known_adapters()
    m = write_mocap(tmp_path, depth=False, overlap=False)
    doc = yaml.safe_load(m.read_text())
    doc.update(adapter="toy", flavour="mint")
    m.write_text(yaml.safe_dump(doc))
    assert isinstance(load_setting(m), Setting)
    doc["flavour"] = "lemon"
    m.write_text(yaml.safe_dump(doc))
    with pytest.raises(ManifestError, match="flavour: must be mint"):
        load_manifest(m)


def test_broken_entry_point_is_a_clear_error(monkeypatch: pytest.MonkeyPatch) -> None:
    class _EP:
        name = "broken"

        def load(self):
            raise ImportError("no module named broken_pkg")

    monkeypatch.setattr(registry, "entry_points", lambda group: [_EP()])
    with pytest.raises(ManifestError, match="entry point .* failed to load: no module named broken_pkg"):
        get_adapter("broken")


def test_register_adapter_rejects_non_adapters() -> None:
    register_adapter("not-an-adapter", object())
    try:
        with pytest.raises(ManifestError, match="does not implement the Adapter protocol"):
            get_adapter("not-an-adapter")
    finally:
        registry._REGISTERED.pop("not-an-adapter")


# --------------------------------------------------------------------------- example adapter
def _write_kitti(root: Path, n: int = 6) -> list[np.ndarray]:
    seq = root / "sequences" / "00"
    (seq / "image_0").mkdir(parents=True)
    (root / "poses").mkdir()
    rng = np.random.default_rng(2)
    poses = [make_se3(so3_exp([0, 0.05 * k, 0]), [0.0, 0.0, 1.0 * k]) for k in range(n)]
    for k in range(n):
        cv2.imwrite(str(seq / "image_0" / f"{k:06d}.png"), rng.integers(0, 255, (20, 30), dtype=np.uint8))
    (seq / "times.txt").write_text("".join(f"{0.1 * k:.6e}\n" for k in range(n)))
    (seq / "calib.txt").write_text("P0: 25.0 0 14.5 0 0 26.0 9.5 0 0 0 1 0\nP1: 25.0 0 14.5 -10 0 26.0 9.5 0 0 0 1 0\n")
    (root / "poses" / "00.txt").write_text("".join(" ".join(f"{x:.12g}" for x in T[:3].ravel()) + "\n" for T in poses))
    return poses


def test_example_adapter_reads_kitti_layout(tmp_path: Path) -> None:
    poses = _write_kitti(tmp_path / "kitti")
    m = tmp_path / "kitti.yaml"
    m.write_text("name: kitti-split\nadapter: example\ndata_root: kitti\nmetric_depth: none\nencounters:\n"
                 "  - name: k00\n    robots:\n      - {id: a, sequence: '00', frames: [0, 3]}\n"
                 "      - {id: b, sequence: '00', frames: [3, 6]}\n")
    report = LoadReport()
    enc = load_setting(m, report).encounters[0]
    assert enc.n_steps == 3 and enc.robot_ids == ["a", "b"]
    K = enc.robots[0].intrinsics
    assert (K.fx, K.fy, K.cx, K.cy, K.width, K.height) == (25.0, 26.0, 14.5, 9.5, 30, 20)
    np.testing.assert_allclose(enc.gt_T_cj_ci(1, 0, 1), se3_inverse(poses[4]) @ poses[1], atol=1e-9)
    np.testing.assert_allclose(enc.robots[1].stamps_s, [0.3, 0.4, 0.5])
    assert enc.robots[1].image(0).shape == (20, 30, 3)


def test_example_adapter_errors_name_file_and_line(tmp_path: Path) -> None:
    _write_kitti(tmp_path / "kitti")
    pf = tmp_path / "kitti" / "poses" / "00.txt"
    lines = pf.read_text().splitlines()
    lines[2] = "1 0 0 0 0 1 0 0 0 0 2 0"  # scaled rotation
    pf.write_text("\n".join(lines) + "\n")
    m = tmp_path / "kitti.yaml"
    m.write_text("name: k\nadapter: example\ndata_root: kitti\nencounters:\n  - name: k00\n    robots:\n"
                 "      - {id: a, sequence: '00', frames: [0, 3]}\n      - {id: b, sequence: '01'}\n")
    with pytest.raises(ManifestError) as info:
        load_setting(m)
    text = str(info.value)
    assert "00.txt: encounters[0].robots[0].sequence line 3" in text and "orthonormal" in text
    assert "sequences/01/image_0" in text  # the second robot's problem is listed too


# --------------------------------------------------------------------------- synthetic adapter
FAKE_SUITES = {"fixture": {"synthetic-cad": ("cad-intersection", {"seed": 0, "n_frames": 6}),
                           "synthetic-indoor": ("indoor-team", {"seed": 0, "n_frames": 6})}}


def _fake_api(calls: list):
    """Stands in for cerpe.synth.generate_suite: same signature and caching contract, mocap output."""
    def generate_suite(world, out_dir, conf=None, *, force=False, progress=True, setting=None):
        calls.append((world, dict(conf), force))
        out = Path(out_dir)
        if not (out / "manifest.yaml").is_file():
            write_mocap(out, depth=False, overlap=False)
        return out / "manifest.yaml"
    return lambda: (generate_suite, FAKE_SUITES)


def test_synthetic_generates_into_cache_and_loads_as_mocap(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    calls: list = []
    monkeypatch.setattr(synthetic_mod, "_synth_api", _fake_api(calls))
    monkeypatch.setenv("CERPE_CACHE", str(tmp_path / "cache"))
    m = tmp_path / "syn.yaml"
    m.write_text("name: synthetic-cad\nadapter: synthetic\nworld: cad-intersection\nsuite: fixture\nseed: 3\n"
                 "metric_depth: mono-sim\n")
    s1 = load_setting(m)
    assert calls == [("cad-intersection", {"seed": 3, "n_frames": 6}, True)]  # preset args, seed replaced
    assert s1.name == "synthetic-cad" and s1.metric_depth == "mono-sim" and s1.encounters[0].n_steps == 6
    gen = Path(s1.meta["generated_manifest"])
    assert gen == tmp_path / "cache" / "synth" / "fixture" / "cad-intersection-seed3" / "manifest.yaml"


def test_synthetic_generator_failure_is_a_manifest_error(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    from cerpe.errors import CerpeError

    class _Err(CerpeError, ValueError):
        pass

    def boom(world, out_dir, conf=None, **kw):
        raise _Err("impossible world layout")

    monkeypatch.setattr(synthetic_mod, "_synth_api", lambda: (boom, FAKE_SUITES))
    m = tmp_path / "syn.yaml"
    m.write_text(f"name: s\nadapter: synthetic\nworld: indoor-team\nsuite: fixture\ncache_dir: {tmp_path / 'c'}\n")
    with pytest.raises(ManifestError, match="impossible world layout") as info:
        load_setting(m)
    assert info.value.problems[0].file == str(m) and info.value.problems[0].field == "world"


def test_synthetic_against_real_generator_api() -> None:
    """The real cerpe.synth exposes what the adapter calls (skipped until it is in this checkout)."""
    try:
        generate_suite, suites = synthetic_mod._synth_api()
    except ManifestError:
        pytest.skip("cerpe.synth not available")
    for suite in synthetic_mod.SUITES:
        for world in synthetic_mod.WORLDS:
            conf = synthetic_mod.suite_conf(suites, suite, world, 7)
            assert conf["seed"] == 7
    assert callable(generate_suite)


def test_synthetic_manifest_validation(tmp_path: Path) -> None:
    m = tmp_path / "syn.yaml"
    m.write_text("name: s\nadapter: synthetic\nworld: mars\nsuite: huge\nseed: -1\nencounters: []\n")
    with pytest.raises(ManifestError) as info:
        load_manifest(m)
    assert {p.field for p in info.value.problems} == {"world", "suite", "seed", "encounters"}


# --------------------------------------------------------------------------- cerpe check, committed manifests
def test_cerpe_check_exit_codes(tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    good = write_mocap(tmp_path / "good")
    assert cerpe_main(["check", str(good)]) == 0
    out = capsys.readouterr().out
    assert "robots 2" in out and "ordered pairs 12" in out and "overlap: mean 0.417" in out
    assert "steps with overlap >= 0.2: 66.7 %" in out and "viewing angle range" in out
    bad = write_mocap(tmp_path / "bad")
    (tmp_path / "bad" / "enc0" / "r0" / "gt.txt").unlink()
    (tmp_path / "bad" / "enc0" / "r1" / "camera.yaml").write_text("fx: 1\n")
    assert cerpe_main(["check", str(good), str(bad)]) == 2
    err = capsys.readouterr().err
    assert "problem(s)" in err and "gt.txt" in err and "intrinsics.width" in err and "Traceback" not in err


def test_committed_manifests_are_valid() -> None:
    folder = REPO / "datasets_manifest"
    mans = {m.name: m for m in find_manifests(folder)}
    assert {"synthetic-cad", "synthetic-indoor", "openmars", "mocap-team"} <= set(mans)
    assert mans["synthetic-cad"].enabled and mans["synthetic-indoor"].enabled
    assert mans["synthetic-cad"].raw["suite"] == "paper-default"
    assert not mans["openmars"].enabled and not mans["mocap-team"].enabled


def test_disabled_manifest_check_is_schema_only(tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    src = REPO / "datasets_manifest" / "mocap-team.yaml"
    shutil.copy(src, tmp_path / "m.yaml")
    assert cerpe_main(["check", str(tmp_path / "m.yaml")]) == 0
    assert "disabled (not supplied)" in capsys.readouterr().out
    with pytest.raises(ManifestError, match="disabled"):
        load_setting(tmp_path / "m.yaml")

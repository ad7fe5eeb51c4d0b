"""`cerpe check` on depth it cannot trust, on `--frames < 1`, and on `enabled: if-present` manifests."""
from __future__ import annotations

import io
from pathlib import Path

import cv2
import numpy as np
import pytest
import yaml

from cerpe import cli
from cerpe.datasets import ManifestError, find_manifests, load_manifest, load_setting
from cerpe.datasets.cli import check_one
from cerpe.datasets.verify import verify_setting
from test_datasets_fixtures import write_mocap


def _depth_png(root: Path, r: int = 0, k: int = 1) -> Path:
    return sorted((root / "enc0" / f"r{r}" / "depth").iterdir())[k]


def test_8bit_depth_png_is_refused_naming_the_file(tmp_path: Path) -> None:
    m = write_mocap(tmp_path)
    bad = _depth_png(tmp_path)
    cv2.imwrite(str(bad), np.full((24, 32), 200, np.uint8))
    lines = check_one(str(m), None, True, False, out=io.StringIO())
    hits = [ln for ln in lines if str(bad) in ln]
    assert len(hits) == 1 and "8-bit depth" in hits[0], lines
    # the other frames are fine: exactly one problem
    assert len(lines) == 1


@pytest.mark.parametrize("units, ok", [(1000, True), (1, False), (1e6, False)])
def test_implausible_depth_units_name_the_field(tmp_path: Path, units: float, ok: bool) -> None:
    m = write_mocap(tmp_path)  # depth PNGs hold 2000 (mm)
    doc = yaml.safe_load(m.read_text())
    doc["encounters"][0]["robots"][1]["depth_units_per_m"] = units
    m.write_text(yaml.safe_dump(doc))
    lines = check_one(str(m), 2, True, False, out=io.StringIO())
    if ok:
        assert lines == []
        return
    assert len(lines) == 1, lines  # once per robot, not once per frame
    assert "encounters[0].robots[1].depth_units_per_m" in lines[0] and str(m) in lines[0]
    assert f"depth_units_per_m={units:g}" in lines[0]


@pytest.mark.parametrize("n", ["0", "-1", "x"])
def test_check_refuses_frames_below_one(tmp_path: Path, n: str, capsys: pytest.CaptureFixture) -> None:
    m = write_mocap(tmp_path)
    with pytest.raises(SystemExit) as info:
        cli.main(["check", str(m), "--frames", n])
    assert info.value.code == 2
    err = capsys.readouterr().err
    assert "--frames" in err and ">= 1" in err and "OK" not in err
    with pytest.raises(ManifestError, match="frames"):
        verify_setting(load_setting(m), max_frames=0, progress=False)


def test_check_frames_one_checks_one_frame_per_robot(tmp_path: Path) -> None:
    m = write_mocap(tmp_path)
    cv2.imwrite(str(_depth_png(tmp_path, 0, 0)), np.full((24, 32), 9, np.uint8))  # frame 0 is the one sampled
    lines = check_one(str(m), 1, True, False, out=io.StringIO())
    assert len(lines) == 1 and "8-bit" in lines[0]


def _if_present_manifest(tmp_path: Path, root: str) -> Path:
    m = write_mocap(tmp_path / "data")
    doc = yaml.safe_load(m.read_text())
    doc.update(enabled="if-present", data_root=root)
    out = tmp_path / "manifests" / "dev.yaml"
    out.parent.mkdir()
    out.write_text(yaml.safe_dump(doc))
    return out


def test_enabled_if_present_is_enabled_when_the_root_exists(tmp_path: Path) -> None:
    man = load_manifest(_if_present_manifest(tmp_path, "../data"))
    assert man.enabled and man.enabled_if_present
    assert load_setting(man).encounters[0].n_steps == 6


def test_enabled_if_present_without_root_is_not_supplied(tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    path = _if_present_manifest(tmp_path, "../nowhere")
    man = load_manifest(path)  # no error: a missing root means "not supplied"
    assert not man.enabled
    out = io.StringIO()
    assert check_one(str(path), None, True, False, out=out) == []
    assert "not supplied" in out.getvalue() and "if-present" in out.getvalue()
    assert [m.name for m in find_manifests(path.parent)] == ["mocap-fixture"]
    with pytest.raises(ManifestError, match="not present"):
        load_setting(man)
    assert cli.main(["check", str(path)]) == 0
    # an unset variable in data_root is "not present" too
    path.write_text(path.read_text().replace("../nowhere", "${CERPE_SURELY_UNSET_ROOT}/x"))
    assert not load_manifest(path).enabled


def test_enabled_other_strings_are_refused(tmp_path: Path) -> None:
    path = _if_present_manifest(tmp_path, "../data")
    path.write_text(path.read_text().replace("if-present", "maybe"))
    with pytest.raises(ManifestError, match="if-present"):
        load_manifest(path)


def test_every_adapter_goes_through_the_same_checks(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """A third-party adapter whose data names a robot '../r0' (it would write outside the run folder) and
    gives a principal point outside the image: loading for a run and `cerpe check` refuse both alike."""
    import dataclasses

    import cerpe.datasets.registry as registry

    class Renaming:
        name, top_level_fields = "renaming", ()

        def validate(self, manifest):
            return []

        def load(self, manifest, report):
            from cerpe.datasets.mocap import MocapAdapter

            setting = MocapAdapter().load(manifest, report)
            r0, r1 = setting.encounters[0].robots
            r0.robot_id = "../r0"
            r1.intrinsics = dataclasses.replace(r1.intrinsics, cx=900.0)
            return setting

    monkeypatch.setitem(registry._REGISTERED, "renaming", Renaming)
    m = write_mocap(tmp_path)
    m.write_text(m.read_text().replace("adapter: mocap", "adapter: renaming"))
    with pytest.raises(ManifestError) as info:
        load_setting(m)
    probs = info.value.problems
    assert len(probs) == 2 and all(p.file == str(m) for p in probs)
    assert probs[0].field.endswith(".id") and "robot id '../r0'" in probs[0].message
    assert probs[1].field == "encounters[0].robots[1].intrinsics" and "(cx, cy) = (900, 11.5)" in probs[1].message
    assert sorted(check_one(str(m), None, True, False, out=io.StringIO())) == sorted(map(str, info.value.problems))

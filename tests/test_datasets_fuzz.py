"""Malformed manifests and data files: each gives a clear error (file + field), a counted skip or a warning.

Every case starts from a valid mocap dataset (``write_mocap``), breaks one thing,
and checks through both the API (``load_setting``, what ``cerpe run`` loads) and
``cerpe check``'s ``check_one`` that the outcome is one of:

* ``error``: a :class:`ManifestError` whose problems name the expected field and file;
* ``count``: loading succeeds and the degradation is counted (no wrong pose);
* ``warn``: loading succeeds with a warning naming the field (a figure that is legal but suspicious);
* ``verify``: a broken frame a run's sample need not decode: loading without decoding
  succeeds (files are read lazily) and ``cerpe check`` (every frame) reports the file by name.

No case may end in any other exception type.
"""
from __future__ import annotations

import io
from pathlib import Path
from typing import Callable

import numpy as np
import pytest
import yaml

from cerpe.datasets import LoadReport, ManifestError, load_setting
from cerpe.datasets.cli import check_one
from cerpe.datasets.formats import NONFINITE_ROWS
from cerpe.datasets.verify import NO_VALID_DEPTH
from test_datasets_fixtures import write_mocap

R0 = "encounters[0].robots[0]"
R1 = "encounters[0].robots[1]"


def _robot(doc: dict, r: int = 0) -> dict:
    return doc["encounters"][0]["robots"][r]


def _lines(path: Path, fn: Callable[[list[str]], list[str]]) -> None:
    path.write_text("\n".join(fn(path.read_text().splitlines())) + "\n")


def _first_png(root: Path, r: int = 0, kind: str = "rgb", k: int = 1) -> Path:
    return sorted((root / "enc0" / f"r{r}" / kind).iterdir())[k]


def _depth_pngs(root: Path, fn: Callable[[np.ndarray], np.ndarray], frames: slice = slice(None)) -> None:
    import cv2

    for p in sorted((root / "enc0" / "r0" / "depth").iterdir())[frames]:
        cv2.imwrite(str(p), fn(cv2.imread(str(p), cv2.IMREAD_UNCHANGED)))


def _set_cam(root: Path, **kw) -> None:
    p = root / "enc0" / "r0" / "camera.yaml"
    cam = yaml.safe_load(p.read_text())
    cam.update(kw)
    for k, v in list(cam.items()):
        if v is None:
            del cam[k]
    p.write_text(yaml.safe_dump(cam))


def _second_encounter(doc: dict) -> None:
    doc["encounters"].append(dict(doc["encounters"][0]))


def _list_file(root: Path, doc: dict, rows: list[str]) -> None:
    (root / "enc0" / "r0" / "rgb.txt").write_text("\n".join(rows) + "\n")
    _robot(doc)["images"] = "enc0/r0/rgb.txt"


def _rename_images(root: Path, r: int, shift: float) -> None:
    for kind in ("rgb", "depth"):
        for p in sorted((root / "enc0" / f"r{r}" / kind).iterdir(), reverse=True):
            p.rename(p.with_name(f"{float(p.stem) + shift:.6f}{p.suffix}"))


# (id, mutate(root, doc), kind, field substring, file substring ("" = the manifest))
CASES: list[tuple[str, Callable, str, str, str]] = [
    ("top-level-list", lambda r, d: d.clear() or d.update(_list=True), "error", "", "manifest.yaml"),
    ("missing-name", lambda r, d: d.pop("name"), "error", "name", "manifest.yaml"),
    ("name-wrong-type", lambda r, d: d.update(name=12), "error", "name", "manifest.yaml"),
    ("missing-adapter", lambda r, d: d.pop("adapter"), "error", "adapter", "manifest.yaml"),
    ("unknown-adapter", lambda r, d: d.update(adapter="kitty"), "error", "adapter", "manifest.yaml"),
    ("enabled-string", lambda r, d: d.update(enabled="yes"), "error", "enabled", "manifest.yaml"),
    ("metric-depth-bad", lambda r, d: d.update(metric_depth="lidar"), "error", "metric_depth", "manifest.yaml"),
    ("sync-tol-negative", lambda r, d: d.update(sync_tolerance_s=-1), "error", "sync_tolerance_s", "manifest.yaml"),
    ("sync-tol-string", lambda r, d: d.update(sync_tolerance_s="fast"), "error", "sync_tolerance_s", "manifest.yaml"),
    ("evaluation-every-0", lambda r, d: d.update(evaluation={"every": 0}), "error", "evaluation.every", "manifest.yaml"),
    ("unknown-field-typo", lambda r, d: d.update(encounter=[]), "error", "encounter", "manifest.yaml"),
    ("data-root-missing", lambda r, d: d.update(data_root="nowhere"), "error", "data_root", "manifest.yaml"),
    ("data-root-unset-var", lambda r, d: d.update(data_root="${CERPE_SURELY_UNSET}/x"), "error", "data_root", "manifest.yaml"),
    ("encounters-empty", lambda r, d: d.update(encounters=[]), "error", "encounters", "manifest.yaml"),
    ("one-robot", lambda r, d: d["encounters"][0]["robots"].pop(), "error", "encounters[0].robots", "manifest.yaml"),
    ("duplicate-robot-ids", lambda r, d: _robot(d, 1).update(id="r0"), "error", f"{R1}.id", "manifest.yaml"),
    ("duplicate-encounter-names", lambda r, d: _second_encounter(d), "error", "encounters[1].name", "manifest.yaml"),
    ("robot-without-images", lambda r, d: _robot(d).pop("images"), "error", f"{R0}.images", "manifest.yaml"),
    ("trajectory-format-bad", lambda r, d: _robot(d).update(trajectory_format="kitti"), "error", f"{R0}.trajectory_format", "manifest.yaml"),
    ("T-body-cam-scaled", lambda r, d: _robot(d).update(T_body_cam=(2 * np.eye(4)).tolist()), "error", f"{R0}.T_body_cam", "manifest.yaml"),
    ("T-body-cam-shape", lambda r, d: _robot(d).update(T_body_cam=[1, 2, 3]), "error", f"{R0}.T_body_cam", "manifest.yaml"),
    ("window-reversed", lambda r, d: _robot(d).update(window_s=[5, 1]), "error", f"{R0}.window_s", "manifest.yaml"),
    ("interpolate-string", lambda r, d: _robot(d).update(interpolate="yes"), "error", f"{R0}.interpolate", "manifest.yaml"),
    ("image-folder-missing", lambda r, d: _robot(d).update(images="enc0/r0/none"), "error", f"{R0}.images", "enc0/r0/none"),
    ("image-folder-empty", lambda r, d: [p.unlink() for p in (r / "enc0/r0/rgb").iterdir()], "error", f"{R0}.images", "enc0/r0/rgb"),
    ("image-name-not-stamp", lambda r, d: _first_png(r).rename(_first_png(r).with_name("frame.png")), "error", f"{R0}.images", "frame.png"),
    ("trajectory-missing", lambda r, d: (r / "enc0/r0/gt.txt").unlink(), "error", f"{R0}.trajectory", "gt.txt"),
    ("trajectory-non-monotonic", lambda r, d: _lines(r / "enc0/r0/gt.txt", lambda L: L[:3] + [L[4], L[3]] + L[5:]), "error", f"{R0}.trajectory line 5", "gt.txt"),
    ("trajectory-zero-quaternion", lambda r, d: _lines(r / "enc0/r0/gt.txt", lambda L: L[:2] + [" ".join(L[2].split()[:4] + ["0"] * 4)] + L[3:]), "error", f"{R0}.trajectory line 3", "gt.txt"),
    ("trajectory-quaternion-norm-2", lambda r, d: _lines(r / "enc0/r0/gt.txt", lambda L: L[:2] + [" ".join(L[2].split()[:4] + ["0", "0", "0", "2"])] + L[3:]), "error", f"{R0}.trajectory line 3", "gt.txt"),
    ("trajectory-wrong-columns", lambda r, d: _lines(r / "enc0/r0/gt.txt", lambda L: L[:2] + [" ".join(L[2].split()[:5])] + L[3:]), "error", f"{R0}.trajectory line 3", "gt.txt"),
    ("trajectory-not-a-number", lambda r, d: _lines(r / "enc0/r0/gt.txt", lambda L: L[:2] + [L[2].replace(" ", " x", 1)] + L[3:]), "error", f"{R0}.trajectory line 3", "gt.txt"),
    ("trajectory-empty", lambda r, d: (r / "enc0/r0/gt.txt").write_text("# nothing\n"), "error", f"{R0}.trajectory", "gt.txt"),
    ("trajectory-all-nan", lambda r, d: (r / "enc0/r0/gt.txt").write_text("1000 nan 0 0 0 0 0 1\n"), "error", f"{R0}.trajectory", "gt.txt"),
    ("csv-header-missing-columns", lambda r, d: (_robot(d).update(trajectory_format="csv"), _lines(r / "enc0/r0/gt.txt", lambda L: ["t,x,y"] + L[1:])), "error", f"{R0}.trajectory line 1", "gt.txt"),
    ("camera-missing-fx", lambda r, d: _set_cam(r, fx=None), "error", f"{R0}.intrinsics.fx", "camera.yaml"),
    ("camera-distortion-not-numbers", lambda r, d: _set_cam(r, distortion="barrel"), "error", f"{R0}.intrinsics.distortion", "camera.yaml"),
    ("camera-negative-width", lambda r, d: _set_cam(r, width=-32), "error", f"{R0}.intrinsics.width", "camera.yaml"),
    ("camera-not-mapping", lambda r, d: (r / "enc0/r0/camera.yaml").write_text("- 1\n- 2\n"), "error", f"{R0}.intrinsics", "camera.yaml"),
    ("camera-missing-file", lambda r, d: (r / "enc0/r0/camera.yaml").unlink(), "error", f"{R0}.intrinsics", "camera.yaml"),
    ("camera-invalid-yaml", lambda r, d: (r / "enc0/r0/camera.yaml").write_text("fx: [1,\n"), "error", f"{R0}.intrinsics line", "camera.yaml"),
    ("list-file-non-monotonic", lambda r, d: _list_file(r, d, ["1000.1 rgb/1000.100000.png", "1000.0 rgb/1000.000000.png"]), "error", f"{R0}.images line 2", "rgb.txt"),
    ("list-file-missing-image", lambda r, d: _list_file(r, d, ["1000.0 rgb/1000.000000.png", "1000.1 rgb/gone.png"]), "error", f"{R0}.images", "gone.png"),
    ("depth-folder-missing", lambda r, d: _robot(d).update(depth="enc0/r0/nodepth"), "error", f"{R0}.depth", "nodepth"),
    ("overlap-wrong-shape", lambda r, d: np.save(r / "enc0/overlap.npy", np.zeros((3, 2, 2))), "error", "encounters[0].overlap", "overlap.npy"),
    ("overlap-out-of-range", lambda r, d: np.save(r / "enc0/overlap.npy", np.full((6, 2, 2), 1.5)), "error", "encounters[0].overlap", "overlap.npy"),
    ("overlap-truncated", lambda r, d: (r / "enc0/overlap.npy").write_bytes((r / "enc0/overlap.npy").read_bytes()[:40]), "error", "encounters[0].overlap", "overlap.npy"),
    ("no-common-steps", lambda r, d: _rename_images(r, 1, 5.0), "error", "encounters[0].robots", "manifest.yaml"),
    ("window-excludes-all", lambda r, d: _robot(d).update(window_s=[100, 200]), "error", f"{R0}.window_s", "manifest.yaml"),
    ("camera-2-distortion-coefficients", lambda r, d: _set_cam(r, distortion=[0.1, 0.01]), "error", f"{R0}.intrinsics.distortion", "camera.yaml"),
    ("camera-principal-point-outside", lambda r, d: _set_cam(r, cx=30 * 15.5, cy=30 * 11.5), "error", f"{R0}.intrinsics", "camera.yaml"),
    ("camera-duplicate-key", lambda r, d: (r / "enc0/r0/camera.yaml").write_text((r / "enc0/r0/camera.yaml").read_text() + "fx: 300\n"), "error", f"{R0}.intrinsics line 13", "camera.yaml"),
    ("robot-id-with-slash", lambda r, d: _robot(d).update(id="r/0"), "error", f"{R0}.id", "manifest.yaml"),
    ("robot-id-dot-dot", lambda r, d: _robot(d).update(id=".."), "error", f"{R0}.id", "manifest.yaml"),
    ("encounter-name-hidden", lambda r, d: d["encounters"][0].update(name=".enc"), "error", "encounters[0].name", "manifest.yaml"),
    ("sync-tol-1e308", lambda r, d: d.update(sync_tolerance_s=1e308), "error", "sync_tolerance_s", "manifest.yaml"),
    ("depth-8bit-all", lambda r, d: _depth_pngs(r, lambda a: np.full(a.shape, 200, np.uint8)), "error", "enc0/r0/", "depth/1000.000000.png"),
    ("depth-units-1000x", lambda r, d: _robot(d).update(depth_units_per_m=1), "error", f"{R0}.depth_units_per_m", "manifest.yaml"),
    ("image-size-vs-intrinsics", lambda r, d: _set_cam(r, width=64, cx=31.5), "error", "enc0/r0/", "rgb/"),
    ("trajectory-nan-row", lambda r, d: _lines(r / "enc0/r0/gt.txt", lambda L: L[:6] + [" ".join(L[6].split()[:1] + ["nan"] * 7)] + L[7:]), "count", f"r0: {NONFINITE_ROWS}", ""),
    ("trajectory-inf-row", lambda r, d: _lines(r / "enc0/r0/gt.txt", lambda L: L[:6] + [" ".join(L[6].split()[:1] + ["inf"] * 3 + L[6].split()[4:])] + L[7:]), "count", f"r0: {NONFINITE_ROWS}", ""),
    ("depth-all-zero-frame", lambda r, d: _depth_pngs(r, np.zeros_like, slice(0, 1)), "count", f"r0: {NO_VALID_DEPTH}", ""),
    ("depth-units-5x-deep", lambda r, d: _robot(d).update(depth_units_per_m=200), "warn", f"{R0}.depth_units_per_m", "manifest.yaml"),
    ("depth-units-5x-shallow", lambda r, d: _robot(d).update(depth_units_per_m=5000), "warn", f"{R0}.depth_units_per_m", "manifest.yaml"),
    ("trajectory-too-short", lambda r, d: _lines(r / "enc0/r0/gt.txt", lambda L: L[:12]), "count", "r0: frames without ground-truth pose", ""),
    ("depth-file-missing", lambda r, d: _first_png(r, 0, "depth").unlink(), "count", "r0: frames without a depth file", ""),
    ("corrupt-image-bytes", lambda r, d: _first_png(r).write_bytes(b"\x89PNG\r\n\x1a\n garbage"), "verify", "enc0/r0/", "rgb/1000.100000.png"),
    ("corrupt-depth-bytes", lambda r, d: _first_png(r, 0, "depth").write_bytes(b"not a png"), "verify", "enc0/r0/", "depth/1000.100000.png"),
    ("depth-size-mismatch", lambda r, d: __import__("cv2").imwrite(str(_first_png(r, 0, "depth")), np.ones((5, 7), np.uint16)), "verify", "enc0/r0/", "depth/1000.100000.png"),
]


def test_there_are_at_least_65_cases() -> None:
    assert len(CASES) >= 65 and len({c[0] for c in CASES}) == len(CASES)


@pytest.mark.parametrize("case", CASES, ids=[c[0] for c in CASES])
def test_malformed_input_gives_clear_outcome(tmp_path: Path, case, caplog) -> None:
    _, mutate, kind, field, file = case
    m = write_mocap(tmp_path)
    doc = yaml.safe_load(m.read_text())
    mutate(tmp_path, doc)
    m.write_text(yaml.safe_dump(list(doc) if doc.get("_list") else doc, sort_keys=False))
    report = LoadReport()
    if kind == "error":
        with pytest.raises(ManifestError) as info:
            load_setting(m, report)
        probs = info.value.problems
        assert probs, "a ManifestError must carry its problems"
        assert any(field in p.field and file in p.file for p in probs), "\n".join(map(str, probs))
        assert all(p.message for p in probs)
    else:  # what a run checks (a sample of frames); "verify": nothing decoded, files are read lazily
        setting = load_setting(m, report, frames=0 if kind == "verify" else "sample")
        for enc in setting.encounters:
            for rob in enc.robots:
                ok = np.array([rob.has_gt(t) for t in range(len(rob))])
                assert np.all(np.isfinite(rob.T_world_cam[ok])) and np.all(np.isnan(rob.T_world_cam[~ok]))
        if kind == "count":
            assert report.counts[("enc0", field)] >= 1, report.counts
        if kind == "warn":
            assert [w for w in report.warnings if w.field == field and file in w.file], report.warnings
            assert str(report.warnings[0]) in caplog.text  # a run logs it
    out = io.StringIO()
    lines = check_one(str(m), None, True, False, out=out)  # `cerpe check` lists the same problem, no traceback
    if kind == "count":
        assert lines == [] and f"counted: enc0: {field}" in out.getvalue(), (lines, out.getvalue())
    elif kind == "warn":
        assert lines == [] and f"warning: {tmp_path / file}: {field}" in out.getvalue(), (lines, out.getvalue())
    else:
        assert lines and any(field in ln and file in ln for ln in lines), lines


def test_all_problems_are_listed_at_once(tmp_path: Path) -> None:
    m = write_mocap(tmp_path)
    doc = yaml.safe_load(m.read_text())
    doc.update(metric_depth="lidar", sync_tolerance_s=0)
    _robot(doc, 1).update(id="r0", trajectory_format="bad")
    m.write_text(yaml.safe_dump(doc))
    with pytest.raises(ManifestError) as info:
        load_setting(m)
    fields = {p.field for p in info.value.problems}
    assert {"metric_depth", "sync_tolerance_s", f"{R1}.id", f"{R1}.trajectory_format"} <= fields
    # data problems of several robots are collected too
    doc = yaml.safe_load(write_mocap(tmp_path / "b").read_text())
    (tmp_path / "b" / "enc0" / "r0" / "gt.txt").unlink()
    (tmp_path / "b" / "enc0" / "r1" / "camera.yaml").write_text("width: 1\n")
    (tmp_path / "b" / "manifest.yaml").write_text(yaml.safe_dump(doc))
    with pytest.raises(ManifestError) as info:
        load_setting(tmp_path / "b" / "manifest.yaml")
    fields = " ".join(p.field for p in info.value.problems)
    assert f"{R0}.trajectory" in fields and f"{R1}.intrinsics.fx" in fields and f"{R1}.intrinsics.height" in fields


def test_invalid_yaml_manifest_names_the_line(tmp_path: Path) -> None:
    p = tmp_path / "bad.yaml"
    p.write_text("name: x\nadapter: mocap\nencounters: [\n  - {name: a\n")
    with pytest.raises(ManifestError) as info:
        load_setting(p)
    (prob,) = info.value.problems
    assert prob.file == str(p) and prob.field.startswith("line ") and "YAML" in prob.message


def test_duplicate_manifest_key_names_file_key_and_line(tmp_path: Path) -> None:
    """YAML keeps the last of two equal keys without a word; a manifest that says a thing twice is refused."""
    m = write_mocap(tmp_path)
    m.write_text(m.read_text().replace("sync_tolerance_s: 0.02\n", "sync_tolerance_s: 0.02\nname: other\n"))
    line = m.read_text().splitlines().index("name: other") + 1
    with pytest.raises(ManifestError) as info:
        load_setting(m)
    (prob,) = info.value.problems
    assert prob.file == str(m) and prob.field == f"line {line}" and "duplicate key 'name'" in prob.message
    assert "line 1" in prob.message  # where the first one is

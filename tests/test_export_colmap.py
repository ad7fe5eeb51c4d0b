"""`cerpe export`: COLMAP text models that pycolmap reads unchanged, whose poses are the run's estimates
(estimate model) and the dataset's ground truth (gt model); bad input is one clear error."""
from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import pandas as pd
import pytest

pycolmap = pytest.importorskip("pycolmap")  # a dependency of cerpe (pyproject.toml); skip only if broken

from cerpe import cli  # noqa: E402
from cerpe.geometry import se3_inverse  # noqa: E402
from cerpe.pipeline import export as ex  # noqa: E402
from cerpe.pipeline.evaluate import poses_from_columns  # noqa: E402
from cerpe.scene import Encounter, Setting  # noqa: E402

from test_pipeline_run_eval import K, _setting, fake_run  # noqa: E402


def _T(image) -> np.ndarray:
    """COLMAP's cam_from_world of a pycolmap image as a 4x4 matrix (a method since pycolmap 3.12)."""
    cfw = image.cam_from_world() if callable(image.cam_from_world) else image.cam_from_world
    return np.vstack([cfw.matrix(), [0, 0, 0, 1]])


def _rows_pose(row: pd.Series, prefix: str) -> np.ndarray:
    """The ``[4,4]`` pose of one results row's ``<prefix>_*`` columns."""
    return poses_from_columns(row.to_frame().T, prefix)[0]


@pytest.fixture()
def exported(tmp_path: Path, monkeypatch) -> tuple[Path, Path]:
    """A cerpe-labelled fake run (one encounter, 6 steps, estimates from step 2) and its COLMAP export."""
    run = fake_run(tmp_path, monkeypatch, "cerpe", n_steps=6, n_enc=1)
    written = ex.export_colmap(run, tmp_path / "colmap", setting=_setting(n_steps=6, n_enc=1))
    assert written == [tmp_path / "colmap" / "enc0" / r / m for r in ("r0", "r1") for m in ("estimate", "gt")]
    return run, tmp_path / "colmap"


def test_pycolmap_reads_the_models_and_their_poses_are_the_runs(exported) -> None:
    run, out = exported
    steps = pd.read_csv(run / "enc0" / "steps.csv")
    robots = pd.read_csv(run / "enc0" / "robots.csv")
    for ego, other in (("r0", "r1"), ("r1", "r0")):
        est = pycolmap.Reconstruction(str(out / "enc0" / ego / "estimate"))
        gt = pycolmap.Reconstruction(str(out / "enc0" / ego / "gt"))
        # 6 own frames + the other's frames at the 4 steps with an estimate; no 3D points
        assert est.num_images() == gt.num_images() == 10 and est.num_points3D() == 0
        cam = est.cameras[1]
        assert cam.model.name == "PINHOLE" and (cam.width, cam.height) == (K.width, K.height)
        np.testing.assert_allclose(cam.params, [K.fx, K.fy, K.cx + 0.5, K.cy + 0.5])  # COLMAP's pixel centres
        e_ims = {im.name: im for im in est.images.values()}
        g_ims = {im.name: im for im in gt.images.values()}
        assert set(e_ims) == set(g_ims)
        for t in range(6):
            odo = robots[(robots["robot"] == ego) & (robots["step"] == t)].iloc[0]
            own = f"{ego}/{t:06d}_frame.png"
            np.testing.assert_allclose(_T(e_ims[own]), se3_inverse(_rows_pose(odo, "odom")), atol=1e-9)
            row = steps[(steps["ego"] == ego) & (steps["step"] == t)].iloc[0]
            name = f"{other}/{t:06d}_frame.png"
            if t < 2:
                assert name not in e_ims  # no estimate at steps 0, 1
                continue
            # the model's relative pose of the two cameras is the estimate, and in the gt model the truth
            np.testing.assert_allclose(_T(e_ims[name]) @ se3_inverse(_T(e_ims[own])), _rows_pose(row, "est"),
                                       atol=1e-9)
            np.testing.assert_allclose(_T(g_ims[name]) @ se3_inverse(_T(g_ims[own])), _rows_pose(row, "gt"),
                                       atol=1e-9)
        np.testing.assert_allclose(_T(g_ims[f"{ego}/000000_frame.png"]), np.eye(4), atol=1e-12)  # gt world: cam 0


def test_the_images_beside_the_models_are_the_pixels_cerpe_read(exported) -> None:
    run, out = exported
    setting = _setting(n_steps=6, n_enc=1)
    r1 = setting.encounters[0].robots[1]
    for t in (0, 3):
        png = cv2.imread(str(out / "enc0" / "images" / "r1" / f"{t:06d}_frame.png"), cv2.IMREAD_COLOR)[:, :, ::-1]
        np.testing.assert_array_equal(png, r1.images[t])


def test_image_names_are_unique_per_robot_and_step_and_hold_no_whitespace() -> None:
    assert ex.image_name("r0", 7, "/data/seq a/rgb/1.png") == "r0/000007_1.png"
    assert ex.image_name("r0", 7, "/data/rgb/my frame.png") == "r0/000007_my_frame.png"
    assert ex.image_name("r1", 7, "/data/rgb/my frame.png") != ex.image_name("r0", 7, "/data/rgb/my frame.png")
    assert ex.image_name("r1", 12, np.zeros((2, 2, 3))) == "r1/000012_frame.png"


def test_a_run_without_odometry_is_refused_naming_the_method(tmp_path: Path, monkeypatch) -> None:
    run = fake_run(tmp_path, monkeypatch, "sift-ransac", n_steps=4, n_enc=1)
    robots = pd.read_csv(run / "enc0" / "robots.csv")
    robots[[c for c in robots.columns if c.startswith("odom_")]] = np.nan  # what a baseline writes
    robots.to_csv(run / "enc0" / "robots.csv", index=False)
    with pytest.raises(ex.ExportError, match="'sift-ransac' writes no odometry"):
        ex.export_colmap(run, tmp_path / "out", setting=_setting(n_steps=4, n_enc=1))


def test_bad_requests_are_one_clear_error(tmp_path: Path, monkeypatch, capsys) -> None:
    run = fake_run(tmp_path, monkeypatch, "cerpe", n_steps=4, n_enc=1)
    s = _setting(n_steps=4, n_enc=1)
    with pytest.raises(ex.ExportError, match="no encounter 'nope'; the run has: enc0"):
        ex.export_colmap(run, tmp_path / "out", encounters=["nope"], setting=s)
    with pytest.raises(ex.ExportError, match="no robot 'r9'; robots: r0, r1"):
        ex.export_colmap(run, tmp_path / "out", egos=["r9"], setting=s)
    renamed = Setting("toy", [Encounter("elsewhere", s.encounters[0].robots)])
    with pytest.raises(ex.ExportError, match="no encounter 'enc0' in the manifest"):
        ex.export_colmap(run, tmp_path / "out", setting=renamed)
    # the manifest run.json names is gone: the CLI says so in one line, exit 2, no traceback
    meta = json.loads((run / "run.json").read_text())
    meta["manifest"] = str(tmp_path / "moved.yaml")
    (run / "run.json").write_text(json.dumps(meta))
    assert cli.main(["export", str(run)]) == 2
    err = capsys.readouterr().err
    assert "field 'manifest'" in err and "moved.yaml not found" in err and "Traceback" not in err
    assert cli.main(["export", str(run), "--manifest", str(tmp_path / "none.yaml")]) == 2
    assert "--manifest: manifest" in capsys.readouterr().err


def test_an_online_robots_run_folder_exports_that_robot_only(tmp_path: Path, monkeypatch) -> None:
    """`cerpe online` writes one run folder per robot, with only that robot as ego: its model, no empty others."""
    run = fake_run(tmp_path, monkeypatch, "cerpe", n_steps=4, n_enc=1)
    for name, col in (("robots.csv", "robot"), ("steps.csv", "ego")):
        df = pd.read_csv(run / "enc0" / name)
        df[df[col] == "r1"].to_csv(run / "enc0" / name, index=False)
    done = json.loads((run / "enc0" / "DONE.json").read_text())
    done["n_pair_rows"] = 4
    (run / "enc0" / "DONE.json").write_text(json.dumps(done))
    written = ex.export_colmap(run, tmp_path / "out", setting=_setting(n_steps=4, n_enc=1))
    assert written == [tmp_path / "out" / "enc0" / "r1" / "estimate", tmp_path / "out" / "enc0" / "r1" / "gt"]
    assert pycolmap.Reconstruction(str(written[0])).num_images() == 4 + 2  # its 4 frames, r0's at steps 2, 3

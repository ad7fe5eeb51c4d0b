"""`cerpe demo`: its core on a tiny encounter (table, picture, reuse), its summary table and its errors."""
from __future__ import annotations

import numpy as np
import pandas as pd
import pytest

from cerpe import cli
from cerpe.demo import COLUMNS, DemoConfig, DemoError, run_demo, summary_table

TINY = DemoConfig(size=(160, 120), frames=5, fps=3.0)


def test_demo_core_writes_table_and_picture_and_reuses_them(tmp_path) -> None:
    out = tmp_path / "demo"
    res = run_demo(out, TINY, progress=False)
    assert res.table_path.is_file() and res.figure_path.is_file()
    assert res.figure_path.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    table = pd.read_csv(res.table_path)
    assert list(table.columns) == list(COLUMNS)
    assert list(table["method"]) == ["CERPE", "ALIKED+LG (SuperGlue stand-in)"]
    assert (table["frames"] == 2 * TINY.frames).all()  # two ordered pairs per step
    assert (table["estimates"] == table["direct"] + table["propagated"]).all()
    assert np.isnan(table["e_pos m"].iloc[1])  # the baseline has no metric scale
    for line in ("CERPE", "success %", "right %"):
        assert line in res.text
    # a second run renders and runs nothing: the world and both runs are reused as they are
    done = {m: (p / "cad-l0-s3-e00" / "DONE.json").read_text() for m, p in res.run_dirs.items()}
    world = (out / "world" / "meta.json").stat().st_mtime_ns
    again = run_demo(out, TINY, progress=False)
    assert {m: (p / "cad-l0-s3-e00" / "DONE.json").read_text() for m, p in again.run_dirs.items()} == done
    assert (out / "world" / "meta.json").stat().st_mtime_ns == world
    pd.testing.assert_frame_equal(again.table, res.table)


def _frame(method: str, step: int, source: str, e_rot: float, metric: bool) -> dict:
    ok = source != "none"
    return {"method": method, "step": step, "source": source, "success": ok,
            "e_rot_rad": e_rot if ok else np.nan, "e_pos_m": 1.0 if ok and metric else np.nan,
            "e_pos_gt_scale_m": 0.5 if ok else np.nan, "after_covis": True}


def test_summary_table_counts_and_means() -> None:
    frames = pd.DataFrame([_frame("cerpe", 0, "none", 0, True), _frame("cerpe", 1, "direct", 0.1, True),
                           _frame("cerpe", 2, "propagated", 0.2, True), _frame("cerpe", 3, "propagated", 0.5, True),
                           _frame("sift-ransac", 0, "direct", 1.0, False),
                           _frame("sift-ransac", 1, "direct", 0.0, False)])
    t = summary_table(frames).set_index("method")
    c, s = t.loc["CERPE"], t.loc["SIFT+RANSAC"]
    assert (c["frames"], c["estimates"], c["direct"], c["propagated"]) == (4, 3, 1, 2)
    assert c["success %"] == pytest.approx(75.0) and c["right %"] == pytest.approx(50.0)  # 0.5 rad is wrong
    assert c["e_rot rad"] == pytest.approx(0.8 / 3) and c["e_pos m"] == pytest.approx(1.0)
    assert (s["success %"], s["right %"]) == (pytest.approx(100.0), pytest.approx(50.0))
    assert np.isnan(s["e_pos m"]) and s["e_pos m (true distance)"] == pytest.approx(0.5)


def test_demo_refuses_a_foreign_folder_and_a_bad_baseline(tmp_path, capsys) -> None:
    (tmp_path / "notes.txt").write_text("mine")
    with pytest.raises(DemoError, match="not a demo folder"):
        run_demo(tmp_path, TINY, progress=False)
    assert cli.main(["demo", "--out", str(tmp_path / "d"), "--baseline", "co-visnet"]) == 2
    assert "--baseline 'co-visnet'" in capsys.readouterr().err
    assert not (tmp_path / "d").exists()  # refused before anything was written

"""The development report: its metrics with known answers, and `cerpe dev` on the fixture suite."""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from cerpe.geometry import make_se3, se3_to_tq_xyzw, so3_exp
from cerpe.pipeline import dev
from cerpe.pipeline.devreport import carried, count_degradation, wrong_runs
from cerpe.pipeline.evaluate import first_covisible_step, frame_errors, summarise

POSE = ("tx", "ty", "tz", "qx", "qy", "qz", "qw")


def _row(step: int, ego: str, other: str, err_rad: float | None, source: str = "direct", anchor: int = -1,
         o_ij: float = 0.5, enc: str = "e") -> dict:
    """A steps.csv row whose estimate is ``err_rad`` off the ground truth in rotation (None: no estimate)."""
    G = make_se3(so3_exp([0.1, 0.2, 0.3]), [1.0, 0.0, 2.0])
    t, q = se3_to_tq_xyzw(G)
    row = {"encounter": enc, "step": step, "stamp_s": float(step), "ego": ego, "other": other,
           "source": source if err_rad is not None else "none", "anchor_step": anchor, "gate_score": 0.5,
           "gate_open": True, "overlap_gt": o_ij}
    row.update({f"gt_{c}": float(v) for c, v in zip(POSE, [*t, *q])})
    if err_rad is None:
        row.update({f"est_{c}": np.nan for c in POSE})
    else:
        E = make_se3(G[:3, :3] @ so3_exp([0.0, 0.0, err_rad]), G[:3, 3])
        te, qe = se3_to_tq_xyzw(E)
        row.update({f"est_{c}": float(v) for c, v in zip(POSE, [*te, *qe])})
    return row


def _steps(rows: list[dict]) -> pd.DataFrame:
    return pd.DataFrame(rows)


def test_wrong_runs_known_answer():
    rows = []
    # r0 about r1: right at 0-1, a direct estimate 0.5 rad off at 2 carried (propagated) to 6,
    # a new wrong anchor at 7 carried to 8, right at 9
    plan = {0: (0.01, "direct", 0), 1: (0.01, "propagated", 0), 2: (0.5, "direct", 2)}
    plan.update({t: (0.5, "propagated", 2) for t in range(3, 7)})
    plan.update({7: (0.6, "direct", 7), 8: (0.6, "propagated", 7), 9: (0.0, "direct", 9)})
    rows += [_row(t, "r0", "r1", e, s, a) for t, (e, s, a) in plan.items()]
    # r1 about r0: wrong at 1 and 3 (a gap between them: two runs), none elsewhere
    rows += [_row(t, "r1", "r0", 0.4 if t in (1, 3) else None, "direct", t) for t in range(10)]
    # another encounter: a per-frame baseline (anchor_step -1) wrong at 4 and 5: every frame its own anchor
    rows += [_row(t, "r0", "r1", 0.9 if t in (4, 5) else 0.0, "direct", -1, enc="b") for t in range(6)]
    runs = wrong_runs(_steps(rows))
    got = sorted(zip(runs["encounter"], runs["ego"], runs["first_step"], runs["n_steps"], runs["anchor_step"]))
    assert got == [("b", "r0", 4, 1, 4), ("b", "r0", 5, 1, 5), ("e", "r0", 2, 5, 2), ("e", "r0", 7, 2, 7),
                   ("e", "r1", 1, 1, 1), ("e", "r1", 3, 1, 3)]
    assert carried(runs) == {"carried_longest_steps": 5, "carried_runs_over_3": 1}
    # exactly 0.3 rad is not "more than 0.3 rad wrong"; no runs at all: zeros
    assert carried(wrong_runs(_steps([_row(t, "r0", "r1", 0.3 - 1e-9) for t in range(5)]))) == {
        "carried_longest_steps": 0, "carried_runs_over_3": 0}


def test_wrong_runs_without_anchor_column_treats_each_frame_alone():
    df = _steps([_row(t, "r0", "r1", 0.5) for t in range(4)]).drop(columns="anchor_step")
    assert carried(wrong_runs(df)) == {"carried_longest_steps": 1, "carried_runs_over_3": 0}


def _pair_steps(overlap01, overlap10, estimate) -> pd.DataFrame:
    """Two directions of one pair; ``estimate[t]``: error in rad or None."""
    rows = []
    for t, (a, b, e) in enumerate(zip(overlap01, overlap10, estimate)):
        rows.append(_row(t, "r0", "r1", e, "direct", t, o_ij=a))
        rows.append(_row(t, "r1", "r0", e, "direct", t, o_ij=b))
    return _steps(rows)


def test_success_after_covisibility_known_answer():
    # co-visible both ways first at step 3 (one way only at step 1); overlap drops again at 5: still "after"
    o01 = [0.0, 0.5, 0.1, 0.3, 0.4, 0.0, 0.3, 0.3, 0.3]
    o10 = [0.0, 0.1, 0.1, 0.25, 0.4, 0.0, 0.3, 0.3, 0.3]
    est = [None, None, None, None, None, 0.01, 0.01, None, 0.01]
    steps = _pair_steps(o01, o10, est)
    assert np.all(first_covisible_step(steps) == 3)
    f = frame_errors(steps, metric_scale=True, every=1)
    s = summarise(f, ["ego"]).set_index("ego")
    assert s.loc["r0", "success_pct"] == pytest.approx(100 * 3 / 9)
    assert s.loc["r0", "success_after_covis_pct"] == pytest.approx(100 * 3 / 6)  # steps 3..8, success at 5, 6, 8
    assert s.loc["r0", "n_frames_after_covis"] == 6
    # every 2nd step evaluated: the first co-visible step (3) is found on all steps; evaluated 4, 6, 8
    s2 = summarise(frame_errors(steps, True, every=2), ["ego"]).set_index("ego")
    assert s2.loc["r1", "success_after_covis_pct"] == pytest.approx(100 * 2 / 3)


def test_success_after_covisibility_is_nan_without_covisible_step_or_ground_truth():
    steps = _pair_steps([0.1] * 4, [0.5] * 4, [0.0] * 4)  # one way only: never co-visible
    s = summarise(frame_errors(steps, True), ["ego"])
    assert s["success_after_covis_pct"].isna().all() and (s["n_frames_after_covis"] == 0).all()
    s = summarise(frame_errors(steps.drop(columns="overlap_gt"), True), ["ego"])
    assert s["success_after_covis_pct"].isna().all() and (s["success_pct"] == 100).all()


def test_right_pct_known_answer():
    # 8 frames: 2 without an estimate, 4 right (0.0, 0.1, 0.29, exactly 0.3), 2 wrong (0.31, 1.2)
    est = [None, 0.0, 0.1, 0.29, 0.3, 0.31, 1.2, None]
    s = summarise(frame_errors(_pair_steps([0.5] * 8, [0.5] * 8, est), True), ["ego"]).set_index("ego")
    assert s.loc["r0", "success_pct"] == pytest.approx(100 * 6 / 8)
    assert s.loc["r0", "right_pct"] == pytest.approx(100 * 4 / 8)
    # a method that answers every frame 1 rad wrong "succeeds" everywhere and is right nowhere
    s = summarise(frame_errors(_pair_steps([0.5] * 4, [0.5] * 4, [1.0] * 4), True), ["ego"])
    assert (s["success_pct"] == 100).all() and (s["right_pct"] == 0).all()


def test_e_pos_on_reference_frames_known_answer():
    """Means over the reference method's frames only (those the method also reports); a method
    answering between them is not charged for it; a set without the reference gets NaN."""
    from cerpe.pipeline.evaluate import e_pos_on_reference_frames

    def rows(method, steps, errs, setting="s"):
        return pd.DataFrame({"setting": setting, "method": method, "encounter": "e", "step": steps, "ego": "r0",
                             "other": "r1", "e_pos_m": errs})

    f = pd.concat([rows("cerpe-wo-em", [0, 3, 6], [0.1, 0.2, np.nan]),  # step 6: no estimate
                   rows("cerpe", [0, 1, 2, 3, 6], [0.3, 5.0, 5.0, 0.5, 0.7]),  # 1, 2 propagated: left out
                   rows("graph", [3], [0.4]),  # reports on one reference frame only
                   rows("cerpe", [0], [9.0], setting="other")], ignore_index=True)
    out = e_pos_on_reference_frames(f).set_index(["setting", "method"])
    assert out.loc[("s", "cerpe-wo-em"), "e_pos_on_ref_frames_m"] == pytest.approx(0.15)
    assert out.loc[("s", "cerpe"), "e_pos_on_ref_frames_m"] == pytest.approx(0.4)  # steps 0 and 3
    assert out.loc[("s", "cerpe"), "n_ref_frames"] == 2
    assert out.loc[("s", "graph"), "e_pos_on_ref_frames_m"] == pytest.approx(0.4)
    other = out.loc[("other", "cerpe")]
    assert np.isnan(other["e_pos_on_ref_frames_m"]) and other["n_ref_frames"] == 0


def test_count_degradation():
    robots = pd.DataFrame({"degradations": ["anchor:inconsistent;msg:lost", np.nan, "",
                                            "anchor:inconsistent;anchor:inconsistent", "anchor:inconsistent-x"]})
    assert count_degradation(robots, "anchor:inconsistent") == 3
    assert count_degradation(robots, "anchor:replaced") == 0
    assert count_degradation(pd.DataFrame({"step": [0]}), "anchor:inconsistent") == 0


# --------------------------------------------------------------------------- the command
def test_dev_refuses_the_paper_seed_and_unknown_methods(tmp_path):
    with pytest.raises(dev.DevError, match="paper-default"):
        dev.dev_report(tmp_path, seeds=[0], synth="fixture", real=False)
    with pytest.raises(dev.DevError, match="--methods"):
        dev.dev_report(tmp_path, methods=["nope"], synth="fixture", real=False)
    with pytest.raises(dev.DevError, match="matches no"):
        dev.dev_report(tmp_path, sets=["no-such-set"], synth="none", manifests_dir=tmp_path)


def test_cli_refuses_seed_zero(capsys):
    from cerpe.cli import main

    assert main(["dev", "--seeds", "0", "--synth", "fixture", "--no-real"]) == 2
    assert "paper-default" in capsys.readouterr().err


@pytest.fixture(scope="module")
def fixture_report(tmp_path_factory):
    """`cerpe dev` on the fixture-sized indoor world (seed 2: its robots see each other) with a development manifest whose data is absent."""
    tmp = tmp_path_factory.mktemp("dev")
    mans = tmp / "manifests"
    mans.mkdir()
    enc = ("encounters:\n  - name: e\n    robots:\n      - {id: a, images: a/rgb, intrinsics: a/camera.yaml}\n"
           "      - {id: b, images: b/rgb, intrinsics: b/camera.yaml}\n")
    (mans / "dev-absent.yaml").write_text(
        "name: dev-absent\nadapter: mocap\nenabled: if-present\ndata_root: ../no-such-data\n" + enc)
    (mans / "other.yaml").write_text("name: other\nadapter: mocap\nenabled: false\n" + enc)
    lines: list[str] = []
    res = dev.dev_report(tmp / "out", seeds=[2], synth="fixture", manifests_dir=mans, label="before",
                         sets=["dev-absent", "dev-fixture-synthetic-indoor-*"], progress=False, echo=lines.append)
    return tmp, res, lines


def test_dev_runs_the_five_methods_and_skips_absent_sets(fixture_report):
    tmp, res, lines = fixture_report
    assert res["errors"] == []
    assert any(ln.startswith("dev-absent: skipped (") and "not present" in ln for ln in lines)
    assert not any("other" in ln.split(":")[0] for ln in lines)  # not a development manifest
    t = res["table"]
    assert list(t["method"]) == list(dev.METHODS) and set(t["set"]) == {"dev-fixture-synthetic-indoor-s2"}
    assert (t["n_frames"] > 0).all() and t["success_pct"].between(0, 100).all()
    # the baselines request an image at every evaluated frame and have no metric scale
    base = t[t["method"].isin(["sift-ransac", "aliked-lightglue"])]
    assert (base["n_requests"] == base["n_frames"]).all() and base["e_pos_m"].isna().all()
    cerpe = t[t["method"] == "cerpe"].iloc[0]  # (at 160x120 it places few views: plumbing, not accuracy)
    assert cerpe["anchors_rejected"] >= 0 and cerpe["bytes_per_robot_step"] > 0
    assert (t["n_frames_after_covis"] > 0).all() and t["success_after_covis_pct"].notna().all()
    woem = t[t["method"] == "cerpe-wo-em"].iloc[0]  # on its own frames it is its own mean
    assert woem["e_pos_on_woem_frames_m"] == pytest.approx(woem["e_pos_m"], nan_ok=True)
    assert base["e_pos_on_woem_frames_m"].isna().all()  # no metric scale: no predicted-scale e_pos
    assert woem["e_pos_gt_scale_on_woem_frames_m"] == pytest.approx(woem["e_pos_gt_scale_m"], nan_ok=True)
    assert len(res["gate"]) == 1 and np.isfinite(res["gate"]["tau"].iloc[0])
    out = tmp / "out"
    for name in ("report.csv", "report.md", "report_gate.csv", "report_checks.csv", "report-before.csv",
                 "report-before.md"):
        assert (out / name).is_file(), name
    # the checks of a synthetic set: no real-set comparison, the carried and graph checks from the table
    checks = res["checks"]
    assert set(checks["check"]) == {"wrong estimate carried", "graph e_pos vs CERPE",
                                    "graph e_pos vs w/o EM, its frames", "graph e_rot / success vs CERPE"}
    assert set(checks["result"]) <= {"pass", "FAIL", "n/a"} and "development checks:" in lines[-3]
    assert list(pd.read_csv(out / "report_checks.csv")["check"]) == list(checks["check"])
    assert pd.read_csv(out / "report-before.csv").shape[0] == len(dev.METHODS) == 5
    md = (out / "report.md").read_text()
    assert "succ>covis %" in md and json.loads(md.split("```json")[1].split("```")[0])["synthetic"]["seeds"] == [2]
    assert "seed 2" in (out / "manifests" / "dev-fixture-synthetic-indoor-s2.yaml").read_text()


def test_dev_reuses_finished_runs(fixture_report, monkeypatch):
    tmp, res, _ = fixture_report
    from cerpe.pipeline import run as rp

    def boom(*a, **k):
        raise AssertionError("a finished run was run again")

    monkeypatch.setattr(rp, "run_methods", boom)
    again = dev.dev_report(tmp / "out", seeds=[2], synth="fixture", manifests_dir=tmp / "manifests",
                           sets=["dev-fixture-synthetic-indoor-*"], progress=False, echo=lambda s: None)
    pd.testing.assert_frame_equal(again["table"], res["table"])


def _method_row(set_name: str, method: str, **kw) -> dict:
    base = {"set": set_name, "method": method, "e_pos_m": float("nan"), "e_pos_gt_scale_m": float("nan"),
            "e_pos_on_woem_frames_m": float("nan"), "e_pos_gt_scale_on_woem_frames_m": float("nan"),
            "e_rot_rad": float("nan"), "e_rot_median_rad": float("nan"), "success_pct": 0.0, "right_pct": 0.0,
            "carried_longest_steps": 0}
    return {**base, **kw}


def test_checks_known_answers() -> None:
    """The development checks on a hand-made table: a real set CERPE wins, one where the baseline's wrong poses
    "succeed" (CERPE places nothing: a failure, not n/a), the graph either side of what it fuses (never worse:
    1.0 x CERPE over all frames, 1.0 x w/o EM over w/o EM's frames), and n/a for a missing method."""
    from cerpe.pipeline.devreport import checks

    t = pd.DataFrame([
        _method_row("win", "cerpe", e_rot_rad=0.02, e_rot_median_rad=0.02, success_pct=64.3, e_pos_m=1.0),
        _method_row("win", "aliked-lightglue", e_rot_rad=1.2, e_rot_median_rad=1.0, success_pct=42.9),
        _method_row("win", "cerpe-wo-em", e_pos_m=0.8, e_rot_rad=0.02, success_pct=50.0, e_pos_on_woem_frames_m=0.8),
        _method_row("win", "cerpe-graph", e_pos_m=0.95, e_rot_rad=0.02, success_pct=64.3,
                    e_pos_on_woem_frames_m=0.81),
        _method_row("room", "cerpe", success_pct=0.0),
        _method_row("room", "aliked-lightglue", e_rot_rad=1.1, e_rot_median_rad=1.2, success_pct=74.0),
        _method_row("dark", "cerpe", e_rot_rad=0.05, e_rot_median_rad=0.04, success_pct=20.0),
        _method_row("dark", "aliked-lightglue", success_pct=0.0),
        _method_row("none", "cerpe"),
        _method_row("none", "aliked-lightglue"),
        _method_row("synth", "cerpe", e_pos_m=0.6, e_rot_rad=0.01, success_pct=60.0, carried_longest_steps=4),
        _method_row("synth", "cerpe-graph", e_pos_m=0.61, e_rot_rad=0.011, success_pct=60.0),
    ])
    c = checks(t, real=["win", "room", "dark", "none"]).set_index(["check", "set"])["result"]
    assert c[("real set: CERPE vs ALIKED+LG", "win")] == "pass"
    assert c[("real set: CERPE vs ALIKED+LG", "room")] == "FAIL"
    assert c[("real set: CERPE vs ALIKED+LG", "dark")] == "pass"  # the baseline has no estimate to compare
    assert c[("real set: CERPE vs ALIKED+LG", "none")] == "n/a"  # neither has one
    assert ("real set: CERPE vs ALIKED+LG", "synth") not in c  # not a real set
    assert c[("wrong estimate carried", "win")] == "pass" and c[("wrong estimate carried", "synth")] == "FAIL"
    assert c[("graph e_pos vs CERPE", "win")] == "pass"  # 0.95 <= 1.0 x 1.0
    assert c[("graph e_pos vs CERPE", "synth")] == "FAIL"  # 0.61 > 1.0 x 0.6
    assert c[("graph e_rot / success vs CERPE", "win")] == "pass" and c[("graph e_rot / success vs CERPE", "synth")] == "FAIL"
    assert ("graph e_pos vs CERPE", "room") not in c  # no cerpe-graph row
    # like for like on w/o EM's frames: 0.81 > 1.0 x 0.8 although the plain e_pos check passes; no w/o EM row: none
    assert c[("graph e_pos vs w/o EM, its frames", "win")] == "FAIL"
    assert ("graph e_pos vs w/o EM, its frames", "synth") not in c
    t.loc[t["set"] == "win", "e_pos_m"] = float("nan")  # no predicted scale (RGB only): the GT-scale figures
    t.loc[(t["set"] == "win") & (t["method"] == "cerpe-graph"), "e_pos_gt_scale_m"] = 0.3
    t.loc[(t["set"] == "win") & (t["method"] == "cerpe"), "e_pos_gt_scale_m"] = 0.25
    t.loc[t["set"] == "win", "e_pos_on_woem_frames_m"] = float("nan")  # no predicted scale on any frame
    c = checks(t, real=["win"]).set_index(["check", "set"])
    assert c.loc[("graph e_pos vs CERPE", "win"), "result"] == "FAIL"  # 0.3 > 1.0 x 0.25
    assert "(GT scale)" in c.loc[("graph e_pos vs CERPE", "win"), "figures"]
    assert c.loc[("graph e_pos vs w/o EM, its frames", "win"), "result"] == "n/a"  # no GT-scale figures either
    t.loc[(t["set"] == "win") & (t["method"] == "cerpe-graph"), "e_pos_gt_scale_on_woem_frames_m"] = 0.2
    t.loc[(t["set"] == "win") & (t["method"] == "cerpe-wo-em"), "e_pos_gt_scale_on_woem_frames_m"] = 0.3
    c = checks(t, real=["win"]).set_index(["check", "set"])
    assert c.loc[("graph e_pos vs w/o EM, its frames", "win"), "result"] == "pass"  # 0.2 <= 1.0 x 0.3
    assert c.loc[("graph e_pos vs w/o EM, its frames", "win"), "figures"] == "0.200 vs 1 x 0.300 (GT scale)"


def test_a_dev_run_exports_to_colmap_through_its_manifest(fixture_report, tmp_path):
    """`cerpe export` on a real CERPE run: the manifest run.json names is loaded (no setting handed in), and the
    models' relative poses are the run's estimates."""
    pycolmap = pytest.importorskip("pycolmap")
    from test_export_colmap import _T, _rows_pose

    from cerpe.geometry import se3_inverse
    from cerpe.pipeline.export import export_colmap

    tmp, res, _ = fixture_report
    run = tmp / "out" / "runs" / "dev-fixture-synthetic-indoor-s2" / "cerpe"
    written = export_colmap(run, tmp_path / "colmap")
    steps = pd.concat(pd.read_csv(p) for p in sorted(run.glob("*/steps.csv")))
    est = steps[np.isfinite(steps["est_qw"])]
    assert len(est) and len(written) == 2 * steps.groupby("encounter")["ego"].nunique().sum()
    row = est.iloc[0]
    model = pycolmap.Reconstruction(str(tmp_path / "colmap" / row["encounter"] / row["ego"] / "estimate"))
    ims = {im.name.split("_")[0]: im for im in model.images.values()}  # "<robot>/<step>" -> image
    step = f"{int(row['step']):06d}"
    rel = _T(ims[f"{row['other']}/{step}"]) @ se3_inverse(_T(ims[f"{row['ego']}/{step}"]))
    np.testing.assert_allclose(rel, _rows_pose(row, "est"), atol=1e-6)

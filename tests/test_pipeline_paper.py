"""Table I assembly, Markdown/LaTeX layout, figure functions and the notebook skip logic."""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from cerpe import plotting
from cerpe.pipeline import notebooks, paper, table1
from cerpe.pipeline import run as rp
from cerpe.runfolder.current import run_is_current

from test_pipeline_run_eval import _setting, fake_prepare


@pytest.fixture()
def ctx(tmp_path, monkeypatch) -> paper.PaperContext:
    monkeypatch.setattr(rp, "prepare_method", fake_prepare())
    m = tmp_path / "toy.yaml"
    m.write_text("name: toy\n")
    s = _setting(n_steps=8)
    c = paper.PaperContext("fixture", "fixture", "offline", tmp_path / "runs", tmp_path / "fig", tmp_path / "tab",
                           tmp_path / "nb")
    c.settings = [paper.SettingEntry("toy", m, "ok", run_manifest=m, setting=s),
                  paper.SettingEntry("openmars", tmp_path / "openmars.yaml", "not supplied",
                                     "fill datasets_manifest/openmars.yaml and set enabled: true")]
    for meth in ("sift-ransac", "cerpe"):
        c.run_dirs[("toy", meth)] = rp.run_method(m, meth, c.runs_root / "toy" / meth, setting=s, progress=False)
    return c


def test_main_results_table(ctx):
    df = table1.main_results(ctx)
    assert list(df.columns[:7]) == ["setting", "method", "e_pos_m", "e_pos_gt_scale_m", "e_rot_rad",
                                    "success_pct", "n_frames"]
    assert len(df) == 2 * len(table1.TABLE_METHODS)
    row = df[(df.setting == "toy") & (df.method == "cerpe")].iloc[0]
    assert row.status == "ok" and row.e_rot_rad == pytest.approx(0.1, abs=1e-6)
    assert row.success_pct == pytest.approx(100 * 6 / 8) and row.n_frames == 2 * 2 * 8
    assert np.isfinite(row.e_pos_m)  # metric method: predicted translation error reported
    # every pair overlaps 0.5 both ways from step 0: success after co-visibility is the success rate
    assert "success_after_covis_pct" in df.columns
    assert row.success_after_covis_pct == pytest.approx(100 * 6 / 8)
    # no w/o EM run in this context: nothing to compare on its frames, NaN rather than a made-up figure
    assert "e_pos_on_woem_frames_m" in df.columns and np.isnan(row.e_pos_on_woem_frames_m)
    sift = df[(df.setting == "toy") & (df.method == "sift-ransac")].iloc[0]
    assert np.isnan(sift.e_pos_m) and np.isfinite(sift.e_pos_gt_scale_m)
    assert (df[df.method.isin(["nope", "co-visnet"]) & (df.setting == "toy")].status == "not available offline").all()
    assert df[df.setting == "openmars"].status.str.startswith("not supplied").all()
    # a method whose run is missing is flagged, never silently empty
    assert df[(df.setting == "toy") & (df.method == "cerpe-wo-em")].status.iloc[0].startswith("error")


def test_markdown_and_latex_layout(ctx, tmp_path):
    df = table1.main_results(ctx)
    paths = table1.write_main_results(df, ctx.tables_dir)
    assert [p.name for p in paths] == ["main_results.csv", "main_results.md", "main_results.tex",
                                       "main_results_notes.md"]
    md = paths[1].read_text()
    assert "n/a" in md and "SuperGlue stand-in (ALIKED+LightGlue)" in md
    head = next(line for line in md.splitlines() if line.startswith("| Method"))
    assert head.count("toy:") == 3 and "openmars" not in head and "covis" not in md  # supplied settings only
    assert head.count("|") == 1 + 1 + 3  # Method and the three columns of the one setting
    # the unsupplied setting: one line under the table, its name and why
    assert md.rstrip().splitlines()[-1] == ("Not shown: openmars (not supplied: fill datasets_manifest/<name>.yaml "
                                            "and set enabled: true).")
    tex = paths[2].read_text()
    for token in (r"\toprule", r"\midrule", r"\bottomrule", r"\multicolumn{3}{c}{toy}", r"\cmidrule(lr){2-4}",
                  "SuperGlue", r"Not shown: openmars"):
        assert token in tex
    assert tex.count(r"\multicolumn{3}") == 1 and r"\begin{tabular}{lccc}" in tex
    back = pd.read_csv(paths[0])  # the long form keeps every setting and its columns
    assert len(back) == len(df) and (back[back.setting == "openmars"].status.str.startswith("not supplied")).all()
    assert list(back.columns) == list(df.columns)


def test_caption_is_short_and_the_rest_is_in_the_notes():
    """At most 80 words; what the rows are goes to tables/README.md (committed) and the notes file."""
    assert len(table1.CAPTION.split()) <= 80
    readme = (Path(paper.ROOT) / "tables" / "README.md").read_text()
    for text in ("ALIKED+LightGlue", "NOPE", "Co-VisNet", "our extension", "GTSAM iSAM2", "main_results_notes.md"):
        assert text in readme


def test_settings_left_out_share_one_line_by_reason():
    rows = [("a", "ok"), ("a", "not available offline"), ("b", "error: run missing (see log)"),
            ("c", "not supplied: fill datasets_manifest/c.yaml and set enabled: true"),
            ("d", "not supplied: fill datasets_manifest/d.yaml and set enabled: true"),
            ("e", "skipped: real datasets are not run in the fixture suite"),
            ("f", "error: f.yaml: data_root not found")]
    df = pd.DataFrame(rows, columns=["setting", "status"])
    assert table1.shown_settings(df) == ["a", "b"]  # a supplied setting whose run is missing shows as error
    assert table1.not_shown_line(df) == (
        "Not shown: c, d (not supplied: fill datasets_manifest/<name>.yaml and set enabled: true); "
        "e (skipped: real datasets are not run in the fixture suite); f (error: <name>.yaml: data_root not found).")
    assert table1.not_shown_line(df[df.setting == "a"]) == ""


def test_figures_written(ctx):
    frames = paper.frames(ctx)
    fig = plotting.error_analysis_figure(frames, title="toy")
    out = plotting.save_figure(fig, ctx.figures_dir / "error_analysis")
    assert all(p.exists() and p.stat().st_size > 1000 for p in out)
    data = paper.qualitative_data(ctx, "toy", methods=("cerpe", "sift-ransac"))
    assert set(data["rel"]) == {"cerpe", "sift-ransac"} and len(data["images"]) >= 1
    plotting.save_figure(plotting.qualitative_figure(**data), ctx.figures_dir / "qualitative_toy")
    com = paper.communication_data(ctx)
    assert com["bytes_table"]["bytes_per_robot_step"].iloc[0] == pytest.approx(100.0)  # descriptor bytes of the fake
    plotting.save_figure(plotting.communication_figure(com["bytes_table"], com["gate"], com["latency"],
                                                       paper=com["paper"]), ctx.figures_dir / "communication_runtime")
    assert (ctx.figures_dir / "communication_runtime.pdf").exists()


def test_notebook_fingerprint_changes_with_runs(ctx):
    fp1 = notebooks.inputs_fingerprint(ctx, {"PROFILE": "fixture"})
    assert fp1 == notebooks.inputs_fingerprint(ctx, {"PROFILE": "fixture"})
    assert fp1 != notebooks.inputs_fingerprint(ctx, {"PROFILE": "paper-default"})
    done = ctx.run_dirs[("toy", "cerpe")] / "enc0" / "DONE.json"
    done.write_text(done.read_text().replace('"n_steps"', '"n_steps" ', 1))
    assert fp1 != notebooks.inputs_fingerprint(ctx, {"PROFILE": "fixture"})


def test_run_is_current(ctx):
    out = ctx.run_dirs[("toy", "sift-ransac")]
    man = ctx.settings[0].run_manifest
    assert run_is_current(out, man, "sift-ransac", "offline")
    man.write_text("name: toy\n# edited\n")
    assert not run_is_current(out, man, "sift-ransac", "offline")


def test_notes_say_what_the_default_cerpe_row_is(tmp_path, monkeypatch):
    """Table I's notes read the CERPE runs' recorded config: no scale step (metric passes), previous frame."""
    recorded = {"tree": {"scale": {"metric_unit": True}, "odometry": {"track_previous": True},
                         "anchors": {"verify": True, "min_inliers": 40}}, "preset": "paper"}
    monkeypatch.setattr(rp, "prepare_method", fake_prepare(recorded))
    m = tmp_path / "toy.yaml"
    m.write_text("name: toy\n")
    c = paper.PaperContext("fixture", "fixture", "offline", tmp_path / "runs", tmp_path / "fig", tmp_path / "tab",
                           tmp_path / "nb")
    c.settings = [paper.SettingEntry("toy", m, "ok", run_manifest=m, setting=_setting(n_steps=4))]
    c.run_dirs[("toy", "cerpe")] = rp.run_method(m, "cerpe", c.runs_root / "toy" / "cerpe",
                                                 setting=c.settings[0].setting, progress=False)
    df = table1.main_results(c)
    md_path, tex_path, notes_path = table1.write_main_results(df, c.tables_dir)[1:]
    notes = notes_path.read_text()
    for text in (notes, df.attrs["cerpe_row_note"]):
        assert "skips the scale step" in text and "metric_unit" in text
        assert "previous frame" in text and "track_previous" in text
        assert "offline models" in text
        assert "only when verified" in text and "fewer than 40 registration inliers" in text
    for text in (md_path.read_text(), tex_path.read_text()):  # not in the caption: it stays short
        assert "skips the scale step" not in text and "tables/README.md" in text
    other = table1.cerpe_row_note("paper", [{"scale": {"metric_unit": True}, "odometry": {"track_previous": False},
                                             "anchors": {"verify": False, "min_inliers": 40}}])
    assert "skips the scale step" not in other and "keyframes, as in the paper" in other
    assert "as in the paper (anchors.verify off)" in other and "registration inliers" not in other
    assert "VGGT" in other


def test_gate_data_and_figure_carry_both_labels(ctx):
    gate = paper.gate_data(ctx)
    row = gate["table"].iloc[0]
    # the toy pairs overlap 0.5 both ways: all positive under both labels, so no ROC curve (one class)
    assert row["covis_n_positive"] == row["covis_n_pairs"] == 2 * 8 and row["n_overlapping"] == row["n_pairs"]
    assert gate["curves_covis"] == {} and gate["curves"] == {}
    table = pd.DataFrame([{"setting": "s", "roc_auc": 0.7, "tau": 0.5, "precision": 0.6, "recall": 0.4,
                           "roc_auc_ceiling": 0.9, "covis_roc_auc": 0.95, "covis_precision": 0.9, "covis_recall": 0.8}])
    curve = (np.array([0.0, 0.2, 1.0]), np.array([0.0, 0.8, 1.0]))
    fig = plotting.gate_figure({"s": curve}, table, gate["points"].assign(setting="s"), curves_covis={"s": curve})
    labels = [t.get_text() for t in fig.axes[0].get_legend().get_texts()]
    assert any("co-visibility label: AUC 0.950, P 0.90 / R 0.80" in t for t in labels)
    assert any("ordered label: AUC 0.700 (symmetric-score ceiling 0.900)" in t for t in labels)
    out = plotting.save_figure(fig, ctx.figures_dir / "gate_quality")
    assert all(p.exists() for p in out)

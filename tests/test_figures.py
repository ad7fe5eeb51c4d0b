"""What a reader of the paper's figures sees: which example a figure shows and why, where its timings
come from, legends outside the data, plain tick labels."""
from __future__ import annotations

import argparse

import numpy as np
import pandas as pd
import pytest

from cerpe import plotting
from cerpe.pipeline import paper
from cerpe.pipeline.bench_report import latency_rows
from cerpe.runfolder.read import timing_note


def test_gate_example_setting_is_the_one_whose_gate_works_best():
    table = pd.DataFrame({"setting": ["sun3d", "indoor", "cad", "tum"], "covis_roc_auc": [np.nan, 0.99, 0.93, np.nan],
                          "roc_auc": [0.42, 0.89, 0.79, np.nan]})
    assert plotting.gate_example_setting(table) == ("indoor", "highest gate ROC AUC (0.990)")
    # where the co-visibility label is undefined, the ordered label's AUC counts
    only_ordered = table.assign(covis_roc_auc=np.nan)
    assert plotting.gate_example_setting(only_ordered)[0] == "indoor"
    assert plotting.gate_example_setting(table.iloc[[0]].assign(covis_roc_auc=np.nan, roc_auc=np.nan)) == (
        "sun3d", "the first (no gate ROC AUC defined)")
    with pytest.raises(plotting.PlotError):
        plotting.gate_example_setting(table.iloc[0:0])


def test_gate_example_pair_shows_the_gate_both_open_and_shut():
    rows = []
    for t in range(10):
        rows.append({"encounter": "e0", "ego": "a", "other": "b", "step": t, "gate_score": 0.9, "gate_open": True,
                     "overlap_gt": 0.5})  # always open: shows no decision
        rows.append({"encounter": "e0", "ego": "b", "other": "a", "step": t, "gate_score": 0.1 * t,
                     "gate_open": t >= 4, "overlap_gt": 0.05 * t})
        rows.append({"encounter": "e1", "ego": "a", "other": "b", "step": t, "gate_score": 0.2, "gate_open": t == 9,
                     "overlap_gt": 0.0})
    g = plotting.gate_example_pair(pd.DataFrame(rows).sample(frac=1, random_state=0), "toy", tau=0.35)
    assert list(g["step"]) == list(range(10)) and g["gate_open"].sum() == 6  # b about a in e0: 6 open, 4 shut
    assert g.attrs == {"label": "gate of b about a (toy/e0)", "tau": 0.35}
    assert list(g.columns) == ["step", "gate_score", "gate_open", "overlap_gt"]


@pytest.mark.parametrize("command, note", [
    ("cerpe/cli.py paper --profile default --jobs 2", "contended: timed during `cerpe paper --jobs 2`, 2 runs side by "
                                                      "side on 2 CPU cores"),
    ("cerpe paper", "contended: timed during `cerpe paper --jobs 2`, 2 runs side by side on 2 CPU cores"),
    ("cerpe paper --jobs 1", "timed during `cerpe paper`, one run at a time"),
    ("cerpe paper --suite fixture --jobs 4", "contended: timed during `cerpe paper --jobs 4`, 4 runs side by side "
                                              "on 2 CPU cores"),
    ("cerpe run datasets_manifest/x.yaml cerpe", "timed while the runs were made, not by `cerpe bench`"),
])
def test_timing_note_says_how_many_runs_shared_the_cores(command, note):
    assert timing_note({"command": command}, 2) == note


def test_timing_note_default_is_cerpe_papers():
    p = argparse.ArgumentParser()
    paper.add_arguments(p)
    assert p.parse_args([]).jobs == 2  # the default timing_note assumes when a command gives no --jobs


def test_latency_rows_of_a_bench_report_are_per_team_step():
    report = {"results": [{"n_robots": 2, "stage_ms": {"encode": {"mean": 10.0}, "backbone": {"mean": 100.0}}},
                          {"n_robots": 3, "stage_ms": {"encode": {"mean": 10.0}}}]}
    rows = pd.DataFrame(latency_rows(report))
    assert rows.set_index(["n_robots", "stage"])["seconds"].to_dict() == pytest.approx(
        {(2, "encode"): 0.02, (2, "backbone"): 0.2, (3, "encode"): 0.03})
    assert latency_rows({}) == []


def _comm_inputs():
    bytes_table = pd.DataFrame({"scheme": ["descriptor + pose only", "CERPE (gated images)", "always send images"],
                                "bytes_per_robot_step": [16_000.0, 90_000.0, 115_000.0]})
    gate = pd.DataFrame({"step": range(6), "gate_score": [0.1, 0.2, 0.5, 0.6, 0.2, 0.1],
                         "gate_open": [False, False, True, True, True, False], "overlap_gt": [0, 0, 0.4, 0.5, 0.1, 0]})
    gate.attrs = {"label": "gate of a about b (toy/e0)", "tau": 0.33}
    return bytes_table, gate


def test_communication_figure_names_team_sizes_and_where_it_was_timed(tmp_path):
    bytes_table, gate = _comm_inputs()
    latency = pd.DataFrame({"n_robots": ["2 (setting-a, setting-b, setting-c)", "2 (setting-a, setting-b, setting-c)",
                                         "3 (setting-d)"], "stage": ["encode", "backbone", "encode"],
                            "seconds": [0.1, 0.3, 0.2]})
    fig = plotting.communication_figure(bytes_table, gate, latency, paper=paper.PAPER_NUMBERS,
                                        runtime_source="contended: 2 runs side by side on 2 CPU cores")
    ax_bytes, ax_gate, ax_time = fig.axes
    assert [t.get_text() for t in ax_time.get_xticklabels()] == ["2 robots", "3 robots"]
    assert "contended" in ax_time.get_title() and "setting-a" not in ax_time.get_xlabel() + ax_time.get_ylabel()
    assert [t.get_text() for t in ax_bytes.get_yticklabels()][0] == "descriptor + pose only"  # top bar, not rotated
    labels = [t.get_text() for t in ax_time.get_legend().get_texts()]
    assert labels[0] == "paper (RTX 4080 laptop, VGGT)" and set(labels[1:]) == {"backbone", "encode"}
    # legends of the data panels sit outside their axes: they cannot cover a point
    fig.canvas.draw()
    for ax in (ax_gate, ax_time):
        assert not ax.get_legend().get_window_extent().overlaps(ax.get_window_extent())
    assert all(p.stat().st_size > 1000 for p in plotting.save_figure(fig, tmp_path / "communication_runtime"))


def test_pareto_figure_plain_log_ticks_and_legend_outside(tmp_path):
    t = pd.DataFrame({"setting": "all", "scheme": ["always", "paper", "pays", "lean", "sift-ransac"],
                      "label": ["always send", "paper's protocol", "ours", "ours, lean", "per-frame SIFT"],
                      "bytes_per_robot_step": [130e3, 96e3, 56e3, 12e3, 115e3],
                      "e_rot_rad": [0.012, 0.013, 0.008, 0.006, 0.19], "e_pos_m": [0.21, 0.2, 0.155, 0.149, np.nan]})
    fig = plotting.pareto_figure(t, "all")
    fig.canvas.draw()
    for ax in fig.axes:
        assert ax.get_legend() is None and ax.get_xscale() == "log"
        ticks = [x.get_text() for x in ax.get_xticklabels() + ax.xaxis.get_minorticklabels() if x.get_text()]
        assert ticks and not any("times" in x or "^" in x or "$" in x for x in ticks), ticks
        assert {"20", "50", "100"} <= set(ticks)
    assert len(fig.legends) == 1 and "not shown (no metric value): sift-ransac" in fig.axes[1].get_title()
    assert all(p.stat().st_size > 1000 for p in plotting.save_figure(fig, tmp_path / "pareto"))


def test_error_analysis_bins_read_as_ranges_and_success_is_shown(tmp_path):
    rng = np.random.default_rng(0)
    n = 60
    frames = pd.DataFrame({"method": np.repeat(["sift-ransac", "cerpe"], n), "success": rng.random(2 * n) > 0.3,
                           "e_rot_rad": np.r_[rng.uniform(0.1, 2, n), rng.uniform(0.002, 0.02, n)],
                           "e_pos_gt_scale_m": np.r_[rng.uniform(0.5, 5, n), rng.uniform(0.01, 0.2, n)],
                           "overlap_gt": np.tile(rng.uniform(0, 1, n), 2),
                           "view_angle_gt": np.tile(rng.uniform(0, 3, n), 2)})
    fig = plotting.error_analysis_figure(frames, title="toy")
    fig.canvas.draw()
    axes = np.array(fig.axes[:6]).reshape(3, 2)
    assert [ax.get_yscale() for ax in axes[:2].ravel()] == ["log"] * 4
    ticks = [t.get_text() for t in axes[2, 0].get_xticklabels()]
    assert ticks[0].startswith("0–0.2\nn=") and ticks[-1].startswith("0.8–1\n")
    assert [t.get_text() for t in axes[2, 1].get_xticklabels()][-1].startswith("2.5–π")
    assert axes[2, 0].get_ylabel() == "success (%)"
    # a setting without overlap ground truth: its panels say so, the angle panels keep their axis labels
    fig = plotting.error_analysis_figure(frames.assign(overlap_gt=np.nan))
    axes = np.array(fig.axes[:6]).reshape(3, 2)
    assert not axes[0, 0].axison and axes[0, 1].get_ylabel().startswith("rotation error")
    assert all(p.stat().st_size > 1000 for p in plotting.save_figure(fig, tmp_path / "error_analysis"))

"""make paper's job list and the worker pool (cerpe.pipeline.schedule)."""
from __future__ import annotations

import pytest

from cerpe.pipeline import paper, schedule

from test_pipeline_run_eval import _setting


def _ctx(tmp_path, name: str) -> paper.PaperContext:
    m = tmp_path / f"{name}.yaml"
    m.write_text(f"name: {name}\n")
    c = paper.PaperContext("paper-default", "paper-default", "offline", tmp_path / "runs", tmp_path / "fig",
                           tmp_path / "tab", tmp_path / "nb")
    c.settings = [paper.SettingEntry(name, m, "ok", run_manifest=m, setting=_setting(n_steps=8))]
    for meth in paper.RUN_METHODS:
        c.run_dirs[(name, meth)] = c.runs_root / name / meth
    return c


def test_jobs_are_the_stale_runs_with_the_cerpe_methods_together(tmp_path):
    ctx = _ctx(tmp_path, "toy")
    current = {"cerpe-graph", "sift-ransac"}
    jobs = schedule.paper_jobs(ctx, lambda out, manifest, m, preset="paper", sets=None: m in current)
    assert sorted(j.name for j in jobs) == ["toy/aliked-lightglue", "toy/cerpe+cerpe-wo-em"]
    ours = next(j for j in jobs if j.name == "toy/cerpe+cerpe-wo-em")
    assert ours.args[1] == ("cerpe", "cerpe-wo-em") and ours.outputs == (("toy", "cerpe"), ("toy", "cerpe-wo-em"))
    # nothing stale, no setting to sweep: no job
    assert schedule.paper_jobs(ctx, lambda *a, **k: True) == []


def test_loss_sweep_waits_for_the_lossless_runs_of_its_setting(tmp_path):
    ctx = _ctx(tmp_path, "synthetic-indoor")
    jobs = {j.name: j for j in schedule.paper_jobs(ctx, lambda out, manifest, m, preset="paper", sets=None: m == "sift-ransac")}
    loss = jobs["message-loss"]
    assert loss.after == ("synthetic-indoor/cerpe+cerpe-wo-em+cerpe-graph",)
    conf, paths, _progress = loss.args
    assert paths["runs"] == ctx.runs_root / "synthetic-indoor" / "message-loss" and conf["models"] == "offline"
    assert set(paths["lossless"]) == {"cerpe", "cerpe-wo-em"}
    # lossless runs already current: it waits for nothing
    jobs = schedule.paper_jobs(ctx, lambda *a, **k: True)
    assert [j.name for j in jobs] == ["message-loss"] and jobs[0].after == ()


def test_a_failed_job_is_one_error_line_and_the_others_go_on(tmp_path):
    bad = tmp_path / "broken.yaml"
    bad.write_text("name: [unclosed\n")
    jobs = [schedule.Job("a", schedule.methods_job, (bad, ("sift-ransac",), tmp_path / "runs", "offline"), 2.0),
            schedule.Job("b", schedule.methods_job, (bad, ("sift-ransac",), tmp_path / "runs", "offline"), 1.0,
                         after=("a",))]
    failed = schedule.run_jobs(jobs, workers=1, progress=False)
    assert [j.name for j, _ in failed] == ["a", "b"]
    assert all("broken.yaml" in err for _, err in failed)


def test_jobs_that_wait_for_each_other_or_for_nothing_known_are_errors(tmp_path):
    def job(name, after):
        return schedule.Job(name, schedule.loss_job, ({}, {}), after=after)

    with pytest.raises(schedule.ScheduleError, match="wait for each other"):
        schedule.run_jobs([job("a", ("b",)), job("b", ("a",))], workers=1, progress=False)
    with pytest.raises(schedule.ScheduleError, match="not jobs"):
        schedule.run_jobs([job("a", ("zzz",))], workers=1, progress=False)


def test_load_job_returns_the_manifest_error(tmp_path):
    bad = tmp_path / "broken.yaml"
    bad.write_text("name: [unclosed\n")
    assert "broken.yaml" in schedule.load_job(bad)

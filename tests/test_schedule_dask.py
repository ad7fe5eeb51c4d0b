"""The same job list on a Dask cluster and on the local executor: the same run folders, dependencies kept.

A LocalCluster of two single-threaded worker processes in the test; the jobs are real `cerpe run`s
(SIFT+RANSAC on two tiny mocap settings). Jobs "a" and "b" write the same run folder, "b" after
"a": run side by side, one would find the folder busy.
"""
from __future__ import annotations

import sys
from pathlib import Path

import pandas as pd
import pytest
import yaml

from cerpe.atomicio import read_json
from cerpe.pipeline import schedule
from test_datasets_fixtures import write_mocap

distributed = pytest.importorskip("distributed")


def _manifests(root: Path) -> list[Path]:
    out = []
    for name in ("toy-a", "toy-b"):
        m = write_mocap(root / name)
        doc = yaml.safe_load(m.read_text())
        doc["name"] = name
        m.write_text(yaml.safe_dump(doc))
        out.append(m)
    return out


def _jobs(manifests: list[Path], runs: Path) -> list[schedule.Job]:
    a, b = manifests
    return [schedule.Job("a", schedule.methods_job, (a, ("sift-ransac",), runs, {}), 2.0),
            schedule.Job("b", schedule.methods_job, (a, ("sift-ransac",), runs, {}), 1.0, after=("a",)),
            schedule.Job("c", schedule.methods_job, (b, ("sift-ransac",), runs, {}), 1.5)]


def _tables(runs: Path) -> dict[str, pd.DataFrame]:
    out = {}
    for f in sorted(runs.glob("*/*/*/*.csv")):
        df = pd.read_csv(f)
        out[str(f.relative_to(runs))] = df[[c for c in df.columns if not (c.startswith("t_") and c.endswith("_s"))]]
    return out


def test_jobs_on_dask_give_the_run_folders_of_the_local_executor(tmp_path):
    manifests = _manifests(tmp_path / "data")
    here = schedule.run_jobs(_jobs(manifests, tmp_path / "here"), workers=1, progress=False)
    assert here == []
    with distributed.LocalCluster(n_workers=2, threads_per_worker=1, processes=True, dashboard_address=None) as cl:
        failed = schedule.run_jobs(_jobs(manifests, tmp_path / "dask"), progress=False, scheduler=cl.scheduler_address)
    assert failed == []
    a, b = _tables(tmp_path / "here"), _tables(tmp_path / "dask")
    assert sorted(a) == sorted(b) and len(a) == 4  # steps.csv and robots.csv of both settings
    for name in a:
        pd.testing.assert_frame_equal(a[name], b[name], check_exact=True)
    for setting in ("toy-a", "toy-b"):
        fp = [read_json(root / setting / "sift-ransac" / "run.json", "run.json")["fingerprint"]
              for root in (tmp_path / "here", tmp_path / "dask")]
        assert fp[0] == fp[1]


def test_scheduler_without_dask_is_one_error_saying_how_to_install_it(monkeypatch, capsys):
    from cerpe.cli import main

    monkeypatch.setitem(sys.modules, "distributed", None)  # `import distributed` fails as if not installed
    assert main(["paper", "--suite", "fixture", "--scheduler", "tcp://127.0.0.1:8786"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "pip install" in err[0] and "dask" in err[0]

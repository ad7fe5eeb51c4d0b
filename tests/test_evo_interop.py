"""evo reads a run folder's TUM files unchanged, and its APE (translation part, no alignment) over
estimate vs ground truth equals `cerpe eval`'s e_pos for the same pair (the README promises both)."""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from evo.core import metrics, sync  # a dev dependency (pyproject.toml): missing is a failure, not a skip
from evo.tools import file_interface as evo_fi

from cerpe.datasets.formats import read_trajectory
from cerpe.pipeline import evaluate as ev

from test_pipeline_run_eval import fake_run


@pytest.fixture()
def run_dir(tmp_path: Path, monkeypatch) -> Path:
    """A CERPE-labelled run (metric translation) of the fake method: rotation off by 0.1 rad, translation doubled."""
    return fake_run(tmp_path, monkeypatch, "cerpe", n_steps=8, n_enc=1)


def test_evo_reads_every_tum_file_of_a_run(run_dir: Path) -> None:
    files = sorted((run_dir / "enc0" / "poses").glob("*.tum")) + sorted((run_dir / "enc0" / "odometry").glob("*.tum"))
    assert len(files) == 2 * 2 + 2  # estimate + ground truth per ordered pair, odometry per robot
    for f in files:
        traj = evo_fi.read_tum_trajectory_file(f)
        ours = read_trajectory(f, "tum", "test")
        assert traj.num_poses == len(ours.stamps_s) > 0
        np.testing.assert_allclose(traj.timestamps, ours.stamps_s, atol=1e-9)
        np.testing.assert_allclose(np.stack(traj.poses_se3), ours.T_world_body, atol=1e-7)


@pytest.mark.parametrize("ego,other", [("r0", "r1"), ("r1", "r0")])
def test_evo_ape_translation_equals_cerpe_e_pos(run_dir: Path, ego: str, other: str) -> None:
    poses = run_dir / "enc0" / "poses"
    gt = evo_fi.read_tum_trajectory_file(poses / f"{ego}__{other}.gt.tum")
    est = evo_fi.read_tum_trajectory_file(poses / f"{ego}__{other}.tum")
    gt, est = sync.associate_trajectories(gt, est, max_diff=1e-3)
    ape = metrics.APE(metrics.PoseRelation.translation_part)
    ape.process_data((gt, est))
    evo_mean = ape.get_statistic(metrics.StatisticsType.mean)

    frames, _ = ev.evaluate_runs([run_dir])
    pair = frames[(frames["ego"] == ego) & (frames["other"] == other) & frames["success"]]
    assert len(pair) == gt.num_poses == 6  # steps 2..7 have an estimate
    assert evo_mean > 0.1  # the fake doubles the translation: a real error to agree on
    assert evo_mean == pytest.approx(pair["e_pos_m"].mean(), rel=1e-6)
    np.testing.assert_allclose(np.sort(ape.error), np.sort(pair["e_pos_m"].to_numpy()), rtol=1e-6)

"""Run folders and the paper's metrics: known answers, resume, refusal of mixed configs."""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from cerpe.datasets.formats import read_trajectory
from cerpe.geometry import make_se3, paper_T_ij, random_se3, se3_to_tq_xyzw, so3_exp
from cerpe.pipeline import evaluate as ev
from cerpe.pipeline import run as rp
from cerpe.runfolder import write
from cerpe.runfolder.layout import PEER_OVERLAP_CSV
from cerpe.records import PairRecord, RobotRecord, StepResult
from cerpe.scene import CameraIntrinsics, Encounter, RobotStream, Setting

K = CameraIntrinsics(100.0, 100.0, 31.5, 23.5, 64, 48)


def _setting(n_steps: int = 6, n_enc: int = 2, seed: int = 0) -> Setting:
    rng = np.random.default_rng(seed)
    encs = []
    for e in range(n_enc):
        robots = []
        for r in range(2):
            T = np.stack([random_se3(rng, 3.0) for _ in range(n_steps)])
            imgs = [rng.integers(0, 255, (48, 64, 3), dtype=np.uint8) for _ in range(n_steps)]
            robots.append(RobotStream(f"r{r}", K, np.arange(n_steps) * 0.1 + 100.0, imgs, T))
        ov = np.full((n_steps, 2, 2), 0.5)
        encs.append(Encounter(f"enc{e}", robots, overlap=ov))
    return Setting("toy", encs)


def _fake_steps(fail_first: int = 2, noise_rad: float = 0.1):
    """A fake method: the GT pose rotated by ``noise_rad`` about z, translation doubled; none before ``fail_first``."""

    def steps(enc: Encounter):
        for t in range(enc.n_steps):
            pairs = []
            for i, j in enc.ordered_pairs():
                G = enc.gt_T_cj_ci(t, i, j)
                T = None
                if t >= fail_first:
                    T = make_se3(G[:3, :3] @ so3_exp([0, 0, noise_rad]), 2.0 * G[:3, 3])
                pairs.append(PairRecord(t, float(enc.robots[i].stamps_s[t]), enc.robots[i].robot_id,
                                        enc.robots[j].robot_id, 0.5, True, "direct" if T is not None else "none", T))
            robots = [RobotRecord(t, float(r.stamps_s[t]), r.robot_id, r.T_world_cam[t], 1.0, 1, False,
                                  {"descriptor": 100}, {"backbone": 0.01}) for r in enc.robots]
            yield StepResult(t, pairs, robots)

    return steps


def fake_prepare(recorded: dict | None = None):
    """A stand-in for ``run.prepare_method``: the fake method, recording ``recorded`` as its config."""
    return lambda method, seed, depth=None, every=1, depth_options=None, channel=None, preset="paper", sets=None: (
        recorded or {"fake": True}, _fake_steps())


def fake_run(tmp_path: Path, monkeypatch, method: str = "sift-ransac", **setting_kw) -> Path:
    """A finished run folder ``tmp_path/run`` of the fake method under ``method``'s name."""
    monkeypatch.setattr(rp, "prepare_method", fake_prepare())
    m = tmp_path / "toy.yaml"
    m.write_text("name: toy\nadapter: example\n")
    return rp.run_method(m, method, tmp_path / "run", setting=_setting(**setting_kw), progress=False)


@pytest.fixture()
def manifest(tmp_path: Path) -> Path:
    m = tmp_path / "toy.yaml"
    m.write_text("name: toy\nadapter: example\nevaluation: {every: 1}\n")
    return m


@pytest.fixture()
def fake_method(monkeypatch):
    monkeypatch.setattr(rp, "prepare_method", fake_prepare())


def test_run_folder_layout_and_known_metrics(tmp_path, manifest, fake_method):
    out = rp.run_method(manifest, "sift-ransac", tmp_path / "run", setting=_setting(), progress=False)
    meta = json.loads((out / "run.json").read_text())
    assert meta["method"] == "sift-ransac" and meta["fingerprint"] and meta["package_versions"]["numpy"]
    for enc in ("enc0", "enc1"):
        assert (out / enc / "DONE.json").exists()
        steps = pd.read_csv(out / enc / "steps.csv")
        assert len(steps) == 6 * 2
        assert {"gate_score", "gate_open", "source", "bytes_pair", "overlap_gt", "view_angle_gt",
                "t_backbone_s", "gt_tx", "est_qw"} <= set(steps.columns)
        tum = (out / enc / "poses" / "r0__r1.tum").read_text().splitlines()
        assert tum[0].startswith("#") and len(tum) == 1 + 4  # steps 2..5 have estimates
        assert len(tum[1].split()) == 8
    frames, _ = ev.evaluate_runs([out])
    table = ev.summarise(frames, ["setting", "method"])
    row = table.iloc[0]
    # 2 of 6 steps fail in every pair -> 66.7 %; rotation error exactly 0.1 rad
    assert row["success_pct"] == pytest.approx(100 * 4 / 6)
    assert row["e_rot_rad"] == pytest.approx(0.1, abs=1e-6)
    assert row["n_frames"] == 2 * 2 * 6
    # baselines have no metric scale: predicted e_pos is NaN, GT-scale translation error is ~0
    assert np.isnan(row["e_pos_m"])
    assert row["e_pos_gt_scale_m"] == pytest.approx(0.0, abs=1e-6)


def test_tum_roundtrip_matches_steps(tmp_path, manifest, fake_method):
    s = _setting()
    out = rp.run_method(manifest, "sift-ransac", tmp_path / "run", setting=s, progress=False)
    tr = read_trajectory(out / "enc0" / "poses" / "r1__r0.gt.tum", "tum", "gt")
    stamps, T = tr.stamps_s, tr.T_world_body
    enc = s.encounters[0]
    for k, st in enumerate(stamps):
        t = int(np.argmin(np.abs(enc.robots[1].stamps_s - st)))
        np.testing.assert_allclose(T[k], enc.gt_T_cj_ci(t, 1, 0), atol=1e-7)


def test_csv_keeps_epoch_stamps_to_the_nanosecond():
    """steps.csv / robots.csv: an epoch stamp (TUM's 1305031102.175303936) reads back within 1 us, not
    rounded to 10 s as 9 significant digits would; a missing stamp stays missing; other floats keep 9 digits."""
    import io

    text = write.csv_text([{"step": 0, "stamp_s": 1305031102.175303936, "x": 1 / 3},
                         {"step": 1, "stamp_s": float("nan"), "x": 2.0}])
    back = pd.read_csv(io.StringIO(text))
    assert abs(back["stamp_s"][0] - 1305031102.175303936) < 1e-6 and np.isnan(back["stamp_s"][1])
    assert back["x"][0] == pytest.approx(1 / 3, rel=1e-8) and "0.333333333" in text


def test_resume_skips_finished_and_recomputes_unfinished(tmp_path, manifest, fake_method, monkeypatch):
    s = _setting()
    out = rp.run_method(manifest, "sift-ransac", tmp_path / "run", setting=s, progress=False)
    done0 = (out / "enc0" / "DONE.json").read_text()
    (out / "enc1" / "DONE.json").unlink()  # enc1 interrupted
    (out / "enc1" / "steps.csv").write_text("encounter,step\nenc1,0\nenc1,")  # half-written
    calls = []
    real = write.run_encounter_to_folder

    def spy(enc, *a, **k):
        calls.append(enc.name)
        return real(enc, *a, **k)

    monkeypatch.setattr(write, "run_encounter_to_folder", spy)
    with pytest.raises(ev.EvalError, match="enc1.*not finished"):
        ev.load_run(out)
    rp.run_method(manifest, "sift-ransac", out, setting=s, progress=False)
    assert calls == ["enc1"]
    assert (out / "enc0" / "DONE.json").read_text() == done0
    assert len(ev.load_run(out).steps) == 2 * 12


def test_other_configuration_is_refused(tmp_path, manifest, fake_method):
    s = _setting()
    out = rp.run_method(manifest, "sift-ransac", tmp_path / "run", setting=s, progress=False)
    with pytest.raises(rp.RunError, match="another configuration"):
        rp.run_method(manifest, "sift-ransac", out, setting=s, seed=7, progress=False)
    rp.run_method(manifest, "sift-ransac", out, setting=s, seed=7, overwrite=True, progress=False)
    assert json.loads((out / "run.json").read_text())["seed"] == 7


def test_a_run_folder_of_an_older_version_is_refused_with_how_to_rerun_it(tmp_path, manifest, fake_method):
    s = _setting()
    out = rp.run_method(manifest, "sift-ransac", tmp_path / "run", setting=s, progress=False)
    meta = json.loads((out / "run.json").read_text())
    meta["config"]["format"] = 1
    (out / "run.json").write_text(json.dumps(meta))
    with pytest.raises(rp.RunError, match=r"another version of cerpe \(run format 1, this one writes 2\); rerun "
                                          r"with --overwrite"):
        rp.run_method(manifest, "sift-ransac", out, setting=s, progress=False)
    from cerpe.runfolder.current import run_is_current

    assert not run_is_current(out, manifest, "sift-ransac")  # never silently reused
    rp.run_method(manifest, "sift-ransac", out, setting=s, overwrite=True, progress=False)
    assert json.loads((out / "run.json").read_text())["config"]["format"] == rp.RUN_FORMAT


def test_mixed_configurations_never_aggregated(tmp_path, manifest, fake_method):
    s = _setting()
    a = rp.run_method(manifest, "sift-ransac", tmp_path / "a", setting=s, progress=False)
    b = rp.run_method(manifest, "sift-ransac", tmp_path / "b", setting=s, seed=3, progress=False)
    with pytest.raises(ev.EvalError, match="mixed configurations"):
        ev.evaluate_runs([a, b])
    import shutil

    shutil.copytree(a, tmp_path / "a_copy")  # same configuration twice would double-count frames
    with pytest.raises(ev.EvalError, match="given twice"):
        ev.evaluate_runs([a, tmp_path / "a_copy"])
    # an encounter copied in from another configuration's folder
    import shutil

    shutil.rmtree(a / "enc1")
    shutil.copytree(b / "enc1", a / "enc1")
    with pytest.raises(ev.EvalError, match="refusing to mix"):
        ev.load_run(a)


def test_corrupt_results_give_clear_errors(tmp_path, manifest, fake_method):
    out = rp.run_method(manifest, "sift-ransac", tmp_path / "run", setting=_setting(), progress=False)
    (out / "run.json").write_text('{"method": "sift')
    with pytest.raises(ev.EvalError, match="run.json"):
        ev.load_run(out)
    with pytest.raises(ev.EvalError, match="run.json"):
        ev.load_run(tmp_path / "nowhere")


def test_truncated_steps_csv_named(tmp_path, manifest, fake_method):
    out = rp.run_method(manifest, "sift-ransac", tmp_path / "run", setting=_setting(), progress=False)
    p = out / "enc0" / "steps.csv"
    p.write_text("\n".join(p.read_text().splitlines()[:3]) + "\n")
    with pytest.raises(ev.EvalError, match="steps.csv"):
        ev.load_run(out)


def test_unavailable_methods_exit_clearly(tmp_path, manifest, capsys):
    from cerpe.cli import main

    for m in ("nope", "co-visnet"):
        rc = main(["run", str(manifest), "--method", m, "--out", str(tmp_path / m)])
        assert rc == 2
        assert "not available offline" in capsys.readouterr().err
        assert not (tmp_path / m).exists()


def test_missing_manifest_is_clear(tmp_path):
    with pytest.raises(rp.RunError, match="manifest not found"):
        rp.run_method(tmp_path / "nope.yaml", "sift-ransac", tmp_path / "r")


def test_evaluation_every_and_missing_gt(manifest):
    s = _setting(n_steps=6, n_enc=1)
    rows = []
    for res in _fake_steps(fail_first=0, noise_rad=0.0)(s.encounters[0]):
        for pr in res.pairs:
            G = s.encounters[0].gt_T_cj_ci(pr.step, 0 if pr.ego == "r0" else 1, 1 if pr.ego == "r0" else 0)
            r = {"encounter": "enc0", **pr.as_row(), **write.gt_cols(G)}
            rows.append(r)
    df = pd.DataFrame(rows)
    df.loc[df["step"] == 4, [f"gt_{c}" for c in ev.POSE]] = np.nan  # no GT at step 4
    f = ev.frame_errors(df, metric_scale=True, every=2)
    assert sorted(f["step"].unique()) == [0, 2]
    assert f["success"].all()
    # translation doubled -> e_pos = ||t||, GT scale removes it
    np.testing.assert_allclose(f["e_pos_m"], np.linalg.norm(f[["gt_tx", "gt_ty", "gt_tz"]].to_numpy(), axis=1))
    np.testing.assert_allclose(f["e_pos_gt_scale_m"], 0.0, atol=1e-9)


def test_e_rot_matches_roma():
    roma = pytest.importorskip("roma")
    torch = pytest.importorskip("torch")
    rng = np.random.default_rng(3)
    q1 = rng.normal(size=(200, 4))
    q2 = rng.normal(size=(200, 4))
    q1 /= np.linalg.norm(q1, axis=1, keepdims=True)
    q2 /= np.linalg.norm(q2, axis=1, keepdims=True)
    df = pd.DataFrame({"step": 0, "source": "direct",
                       **{f"est_{c}": 0.0 for c in ("tx", "ty", "tz")}, **{f"gt_{c}": 1.0 for c in ("tx", "ty", "tz")},
                       **{f"est_{c}": q1[:, k] for k, c in enumerate(("qx", "qy", "qz", "qw"))},
                       **{f"gt_{c}": q2[:, k] for k, c in enumerate(("qx", "qy", "qz", "qw"))}})
    ours = ev.frame_errors(df, metric_scale=True)["e_rot_rad"].to_numpy()
    ref = roma.unitquat_geodesic_distance(torch.tensor(q1), torch.tensor(q2)).numpy()
    np.testing.assert_allclose(ours, ref, atol=1e-6)


def test_eval_counts_frames_without_gt_and_nonfinite_estimates(tmp_path, manifest, fake_method, caplog, capsys):
    """24 frames, 16 with an estimate (steps 0-1 fail). Two lose their ground truth, two get a non-finite
    estimate: 22 evaluated, 12 successes; n_no_gt and n_nonfinite say why, a warning names each."""
    from cerpe.cli import main

    out = rp.run_method(manifest, "sift-ransac", tmp_path / "run", setting=_setting(), progress=False)
    for enc in ("enc0", "enc1"):
        p = out / enc / "steps.csv"
        df = pd.read_csv(p)
        if enc == "enc0":
            df.loc[df["step"] == 3, [f"gt_{c}" for c in ev.POSE]] = np.nan  # both pairs of step 3
            df.loc[(df["step"] == 4) & (df["ego"] == "r0"), "est_tx"] = np.inf
        else:
            df.loc[(df["step"] == 5) & (df["ego"] == "r1"), "est_qw"] = np.nan
        df.to_csv(p, index=False)
    row = ev.evaluate([out]).iloc[0]
    assert (row["n_frames"], row["n_success"], row["n_no_gt"], row["n_nonfinite"]) == (22, 12, 2, 2)
    assert row["success_pct"] == pytest.approx(100 * 12 / 22)
    assert "2 frame(s) with a non-finite estimate" in caplog.text and "2 frame(s) without ground truth" in caplog.text
    assert main(["eval", str(out)]) == 0
    table = capsys.readouterr().out
    assert "n_no_gt" in table and "n_nonfinite" in table


def _covis_setting() -> Setting:
    """One encounter of 6 steps whose pair is co-visible both ways from step 3 (r0 sees r1 from step 2)."""
    s = _setting(n_steps=6, n_enc=1)
    ov = np.full((6, 2, 2), 0.1)
    ov[2:, 0, 1] = 0.5
    ov[3:, 1, 0] = 0.5
    s.encounters[0].overlap = ov
    return s


def _as_online_robots(run: Path, root: Path, team: str = "lab") -> dict[str, Path]:
    """The folders `cerpe online` writes for the team of ``run`` (one per robot: its own rows, its
    run.json with config.online, its peers' overlap_gt rows about it)."""
    meta = json.loads((run / "run.json").read_text())
    robots = ["r0", "r1"]
    out = {}
    for k, rid in enumerate(robots):
        d = root / rid
        config = {**meta["config"], "online": {"robot": rid, "team": team, "robots": robots,
                                               "link": {"listen": [f"tcp/127.0.0.1:{7447 + k}"]}}}
        fp = f"{rid}-fingerprint"
        (d / "enc0").mkdir(parents=True)
        (d / "run.json").write_text(json.dumps({**meta, "config": config, "fingerprint": fp,
                                                "label": "CERPE (online)"}))
        steps = pd.read_csv(run / "enc0" / "steps.csv")
        mine = steps[steps["ego"] == rid]
        mine.to_csv(d / "enc0" / "steps.csv", index=False)
        rob = pd.read_csv(run / "enc0" / "robots.csv")
        rob[rob["robot"] == rid].to_csv(d / "enc0" / "robots.csv", index=False)
        steps.loc[steps["other"] == rid, ["encounter", "step", "ego", "other", "overlap_gt"]].to_csv(
            d / "enc0" / PEER_OVERLAP_CSV, index=False)
        (d / "enc0" / "DONE.json").write_text(json.dumps({"fingerprint": fp, "n_pair_rows": len(mine)}))
        out[rid] = d
    return out


def test_online_team_folders_evaluate_as_the_team(tmp_path, manifest, fake_method, capsys):
    """The robots' folders of one online team give the table `cerpe run` gives for the team; one robot's
    folder alone has a success after co-visibility (from its peers' overlap rows), NaN without them."""
    from cerpe.cli import main

    ref = rp.run_method(manifest, "cerpe", tmp_path / "run", setting=_covis_setting(), progress=False)
    robots = _as_online_robots(ref, tmp_path / "online")
    team = ev.evaluate(list(robots.values()), by="encounter")
    want = ev.evaluate([ref], by="encounter")
    pd.testing.assert_frame_equal(team, want)
    assert team["success_after_covis_pct"].iloc[0] == pytest.approx(100.0)  # steps 3-5, all with estimates
    assert main(["eval", *map(str, robots.values())]) == 0 and "cerpe" in capsys.readouterr().out
    frames, _ = ev.evaluate_runs([ref])
    for rid, d in robots.items():
        alone = ev.evaluate([d]).iloc[0]
        mine = ev.summarise(frames[frames["ego"] == rid], ["setting", "method"]).iloc[0]
        assert alone["success_after_covis_pct"] == pytest.approx(mine["success_after_covis_pct"])
        assert alone["n_frames_after_covis"] == mine["n_frames_after_covis"] == 3
    (robots["r0"] / "enc0" / PEER_OVERLAP_CSV).unlink()  # what a robot's folder alone gave before
    assert np.isnan(ev.evaluate([robots["r0"]]).iloc[0]["success_after_covis_pct"])
    import shutil

    shutil.copytree(robots["r1"], tmp_path / "r1-again")
    with pytest.raises(ev.EvalError, match="robot 'r1' given twice"):
        ev.evaluate([*robots.values(), tmp_path / "r1-again"])


def test_cerpe_run_ends_with_a_summary_and_refuses_a_loss_seed_without_loss(tmp_path, manifest, fake_method, capsys):
    from cerpe.cli import main
    from cerpe.pipeline.eval_cli import run_summary

    out = rp.run_method(manifest, "sift-ransac", tmp_path / "run", setting=_setting(), progress=False)
    text = run_summary(out)
    assert "frames evaluated" in text and "success" in text and "right" in text and "degradations" in text
    rc = main(["run", str(manifest), "--method", "cerpe", "--out", str(tmp_path / "x"), "--loss-seed", "3"])
    err = capsys.readouterr().err
    assert rc == 2 and "--loss-seed: only with --loss" in err and not (tmp_path / "x").exists()

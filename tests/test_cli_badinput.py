"""The command line as a new user meets it: malformed arguments give one clear line and exit 2,
never a traceback; a closed pipe ends quietly; a sub-command whose import fails stays listed and
says why; -v / -q set the log level."""
from __future__ import annotations

import logging
import os
import subprocess
import sys
from pathlib import Path

import pytest

from cerpe import cli

from test_pipeline_run_eval import fake_run

ROOT = Path(__file__).resolve().parents[1]


def _cli(capsys, *argv: str) -> tuple[int, str]:
    rc = cli.main([str(a) for a in argv])
    err = capsys.readouterr().err
    assert "Traceback" not in err
    return rc, err


@pytest.fixture()
def afile(tmp_path: Path) -> Path:
    f = tmp_path / "afile"
    f.write_text("not a folder\n")
    return f


@pytest.fixture()
def run_dir(tmp_path: Path, monkeypatch) -> Path:
    """A small finished run folder (fake per-frame method)."""
    return fake_run(tmp_path, monkeypatch, n_steps=40, n_enc=2)


@pytest.fixture()
def log_levels():
    """Restore cerpe's logger level after a test that sets it through the CLI."""
    lg = logging.getLogger("cerpe")
    old = lg.level
    yield lg
    lg.setLevel(old)


def test_run_out_is_a_file_or_under_one(capsys, afile, tmp_path):
    manifest = ROOT / "datasets_manifest" / "synthetic-indoor.yaml"
    rc, err = _cli(capsys, "run", manifest, "--method", "sift-ransac", "--out", afile, "--no-progress")
    assert rc == 2 and f"--out {afile}: exists and is not a folder" in err
    rc, err = _cli(capsys, "run", manifest, "--method", "sift-ransac", "--out", afile / "sub", "--no-progress")
    assert rc == 2 and f"{afile} is a file, not a folder" in err
    rc, err = _cli(capsys, "run", manifest, "--method", "cerpe", "--out", tmp_path / "r", "--seed", "-1")
    assert rc == 2 and "--seed -1: must be >= 0" in err
    (tmp_path / "mine").mkdir()
    (tmp_path / "mine" / "thesis.tex").write_text("keep me")
    rc, err = _cli(capsys, "run", manifest, "--method", "sift-ransac", "--out", tmp_path / "mine", "--no-progress")
    assert rc == 2 and "not a run folder" in err and (tmp_path / "mine" / "thesis.tex").exists()


def test_eval_of_a_file_a_manifest_and_bad_csv_targets(capsys, afile, run_dir, tmp_path):
    rc, err = _cli(capsys, "eval", afile)
    assert rc == 2 and f"{afile}: a file, not a run folder" in err
    rc, err = _cli(capsys, "eval", ROOT / "datasets_manifest" / "synthetic-indoor.yaml")
    assert rc == 2 and "not a run folder" in err
    rc, err = _cli(capsys, "eval", tmp_path)  # a folder without run.json
    assert rc == 2 and "run.json" in err
    rc, err = _cli(capsys, "eval", run_dir, "--csv", tmp_path)
    assert rc == 2 and "it is a folder" in err
    rc, err = _cli(capsys, "eval", run_dir, "--csv", afile / "x.csv")
    assert rc == 2 and f"{afile} is a file, not a folder" in err
    rc, _ = _cli(capsys, "eval", run_dir, "--csv", tmp_path / "new" / "table.csv")
    assert rc == 0 and (tmp_path / "new" / "table.csv").is_file()


def test_eval_into_a_closed_pipe_ends_quietly(run_dir):
    """`cerpe eval ... | head`: the reader is gone before cerpe writes; exit like a Unix tool, no traceback."""
    env = {**os.environ, "PYTHONPATH": str(ROOT), "MPLBACKEND": "Agg"}
    proc = subprocess.Popen([sys.executable, "-m", "cerpe.cli", "eval", str(run_dir), "--by", "encounter"],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, env=env, cwd=ROOT)
    proc.stdout.close()  # `head` read nothing and left
    err = proc.stderr.read().decode()
    assert proc.wait(timeout=120) == cli.EXIT_BROKEN_PIPE
    assert "Traceback" not in err and "BrokenPipeError" not in err and "Exception ignored" not in err


@pytest.mark.parametrize("args,match", [
    (["--steps", "0"], "--steps 0: must be >= 1"),
    (["--robots", "1", "3"], "a team has 2 to 8 robots"),
    (["--robots", "2", "9"], "--robots 2 9: a team has 2 to 8 robots"),
    (["--warmup", "5", "--steps", "3"], "leaves none of --steps 3"),
    (["--encounters", "0"], "--encounters 0"),
    (["--width", "0"], "--width 0"),
    (["--synth", "foo"], "expected SETTING:INDEX"),
    (["--synth", "synthetic-foo:0"], "expected SETTING:INDEX"),
    (["--synth", "synthetic-indoor:x"], "expected SETTING:INDEX"),
    (["--synth", "synthetic-indoor:99"], "encounters 0..3"),
    (["--manifest", "no/such/manifest.yaml"], "not found"),
    (["--manifest", "datasets_manifest"], "not a file"),
])
def test_bench_refuses_impossible_options_before_any_work(capsys, monkeypatch, args, match):
    monkeypatch.chdir(ROOT)
    rc, err = _cli(capsys, "bench", *args)
    assert rc == 2 and match in err


def test_bench_out_must_be_a_writable_file_name(capsys, afile, tmp_path):
    rc, err = _cli(capsys, "bench", "--out", tmp_path)
    assert rc == 2 and "is a folder; give a file name" in err
    rc, err = _cli(capsys, "bench", "--out", afile / "b.json")
    assert rc == 2 and f"{afile} is a file, not a folder" in err


@pytest.mark.parametrize("args,match", [
    (["--seed", "-1"], "seed -1: must be >= 0"),
    (["--workers", "0"], "workers 0: must be >= 1"),
    (["--encounters", "2", "--three", "5"], "n_three 5"),
])
def test_synth_refuses_bad_numbers(capsys, tmp_path, args, match):
    rc, err = _cli(capsys, "synth", "cad-intersection", "--out", tmp_path / "s", "--no-progress", *args)
    assert rc == 2 and match in err and not (tmp_path / "s").exists()


def test_synth_out_is_a_file_or_under_one(capsys, afile):
    rc, err = _cli(capsys, "synth", "indoor-team", "--out", afile, "--no-progress")
    assert rc == 2 and "exists and is not a folder" in err
    for world in ("indoor-team", "all"):
        rc, err = _cli(capsys, "synth", world, "--out", afile / "sub", "--no-progress")
        assert rc == 2 and f"{afile} is a file, not a folder" in err


def test_paper_profile_without_weights_is_one_error(capsys, monkeypatch):
    monkeypatch.setenv("CERPE_WEIGHTS_DIR", "/nonexistent-weights")
    rc, err = _cli(capsys, "paper", "--models", "paper", "--suite", "fixture", "--no-progress")
    assert rc == 2 and "the 'paper' profile cannot start" in err and "docs/PAPER_MODELS.md" in err


def test_a_subcommand_whose_import_fails_is_listed_and_says_why(capsys, monkeypatch):
    monkeypatch.setitem(cli.SUBCOMMANDS, "run", ("cerpe.pipeline.no_such_module", "run a method"))
    with pytest.raises(SystemExit):
        cli.main(["--help"])
    out = capsys.readouterr().out
    assert "run" in out and "UNAVAILABLE" in out and "no_such_module" in out
    assert "eval" in out  # the others are still there
    rc, err = _cli(capsys, "run", "x.yaml", "--method", "cerpe", "--out", "somewhere")
    assert rc == 2 and "cerpe run: error: this command is unavailable here" in err and "no_such_module" in err


@pytest.mark.parametrize("flags,level", [([], logging.INFO), (["-v"], logging.DEBUG), (["-q"], logging.WARNING),
                                         (["-qq"], logging.ERROR)])
def test_verbosity_flags_set_the_log_level(capsys, log_levels, flags, level):
    rc, _ = _cli(capsys, *flags, "eval", "no-such-run")
    assert rc == 2 and log_levels.level == level
    rc, _ = _cli(capsys, "eval", "no-such-run", *flags)  # after the sub-command too
    assert rc == 2 and log_levels.level == level


def test_run_set_and_preset_are_checked_before_anything_runs(capsys, tmp_path):
    from cerpe.pipeline.run import parse_sets

    assert parse_sets(["messages.share_estimates=true", "policy.mode=pays", "policy.miss_limit=3",
                       "gate.tau=0.4"]) == {"messages.share_estimates": True, "policy.mode": "pays",
                                            "policy.miss_limit": 3, "gate.tau": 0.4}
    manifest = ROOT / "datasets_manifest" / "synthetic-indoor.yaml"
    for args, match in ((("--set", "share_estimates"), "expected KEY=VALUE"), (("--set", "=1"), "expected KEY=VALUE"),
                        (("--set", "gate.tau=["), "not YAML"),
                        (("--set", "memory.delta_k=abc"), "memory.delta_k: expected int, got 'abc'"),
                        (("--set", "gate.tau=abc"), "gate.tau: expected float | None, got 'abc'"),
                        (("--set", "messages.reply_quality=.nan"), "messages.reply_quality: expected int"),
                        (("--set", "delta_k=2"), "unknown key 'delta_k'; known: gate, memory, scale"),
                        (("--preset", "fast"), "unknown preset 'fast'; known: paper, graph")):
        rc, err = _cli(capsys, "run", manifest, "--method", "cerpe", "--out", tmp_path / "r", *args)
        assert rc == 2 and match in err and len(err.strip().splitlines()) == 1, (args, err)
        assert not (tmp_path / "r").exists()  # refused before any folder is made


# /proc: a folder nobody may write into, not even root (the tests may run as root, which ignores a chmod)
UNWRITABLE = Path("/proc")
needs_proc = pytest.mark.skipif(not (UNWRITABLE / "self").is_dir(), reason="needs Linux /proc")


@needs_proc
def test_synth_and_online_out_where_nothing_can_be_written(capsys, tmp_path):
    """What `cerpe run`, `export` and `eval --csv` already said: one line naming --out, exit 2."""
    rc, err = _cli(capsys, "synth", "indoor-team", "--out", UNWRITABLE / "cerpe-s", "--no-progress")
    assert rc == 2 and f"{UNWRITABLE / 'cerpe-s'}: cannot write into {UNWRITABLE}" in err
    from test_datasets_fixtures import write_mocap

    m = write_mocap(tmp_path / "data")
    rc, err = _cli(capsys, "online", "--robot", "r0", "--manifest", m, "--out", UNWRITABLE / "cerpe-o",
                   "--no-multicast", "--ros-keys", "off")
    assert rc == 2 and f"--out {UNWRITABLE / 'cerpe-o'}: cannot create it" in err
    rc, err = _cli(capsys, "run", m, "--method", "sift-ransac", "--out", UNWRITABLE / "cerpe-r", "--no-progress")
    assert rc == 2 and f"--out {UNWRITABLE / 'cerpe-r'}: cannot create it" in err


def test_online_refuses_unknown_ros_distros_and_lists_every_method(capsys):
    with pytest.raises(SystemExit) as info:
        cli.main(["online", "--robot", "r0", "--manifest", "x.yaml", "--ros-distro", "foxy"])
    err = capsys.readouterr().err
    assert info.value.code == 2 and "'foxy'" in err and all(d in err for d in ("humble", "jazzy", "kilted", "rolling"))
    from cerpe.online import ros

    with pytest.raises(ros.RosError, match="supported: humble, jazzy"):
        ros.type_hash("foxy")
    with pytest.raises(SystemExit):
        cli.main(["online", "--help"])
    help_text = " ".join(capsys.readouterr().out.split())
    assert "cerpe | cerpe-wo-em | cerpe-graph" in help_text and "4 when it finished without ever meeting" in help_text


def _mocap(tmp_path: Path, **robot0) -> Path:
    import yaml
    from test_datasets_fixtures import write_mocap

    m = write_mocap(tmp_path / "data")
    doc = yaml.safe_load(m.read_text())
    doc["encounters"][0]["robots"][0].update(robot0)
    m.write_text(yaml.safe_dump(doc, sort_keys=False))
    return m


def test_run_refuses_what_check_refuses(capsys, tmp_path):
    """8-bit depth and depth_units_per_m 1000x off: `cerpe run` stops before any work, as `cerpe check` does."""
    import cv2
    import numpy as np

    m = _mocap(tmp_path / "units", depth_units_per_m=1)
    for cmd in (["check", m], ["run", m, "--method", "sift-ransac", "--out", tmp_path / "r1", "--no-progress"]):
        rc, err = _cli(capsys, *cmd)
        assert rc == 2 and "encounters[0].robots[0].depth_units_per_m" in err and "2000 m" in err, (cmd, err)
    m = _mocap(tmp_path / "8bit")
    for p in (m.parent / "enc0" / "r0" / "depth").iterdir():
        cv2.imwrite(str(p), np.full((24, 32), 200, np.uint8))
    for cmd in (["check", m], ["run", m, "--method", "sift-ransac", "--out", tmp_path / "r2", "--no-progress"]):
        rc, err = _cli(capsys, *cmd)
        assert rc == 2 and "8-bit depth image" in err, (cmd, err)
    assert not (tmp_path / "r1").exists() and not (tmp_path / "r2").exists()


def test_run_logs_what_loading_counted(capsys, caplog, tmp_path, monkeypatch):
    """Ground-truth rows with NaN or inf: `cerpe check` counts them, `cerpe run` says so too (a warning)."""
    from cerpe.pipeline import run as rp

    from test_pipeline_run_eval import fake_prepare

    m = _mocap(tmp_path)
    gt = m.parent / "enc0" / "r0" / "gt.txt"
    lines = gt.read_text().splitlines()
    lines[5] = lines[5].split()[0] + " nan" * 7
    lines[9] = lines[9].split()[0] + " inf 0 0 " + " ".join(lines[9].split()[4:])
    gt.write_text("\n".join(lines) + "\n")
    monkeypatch.setattr(rp, "prepare_method", fake_prepare())
    rc, _ = _cli(capsys, "run", m, "--method", "sift-ransac", "--out", tmp_path / "r", "--no-progress")
    assert rc == 0 and "r0: ground-truth trajectory rows with NaN or inf (skipped): 2" in caplog.text

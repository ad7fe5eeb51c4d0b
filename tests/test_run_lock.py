"""One writer per run folder: a second `cerpe run` on a busy --out stops at once naming the holder (exit 2),
or waits with --wait; the lock goes with its process, however that process ends."""
from __future__ import annotations

import os
import signal
import subprocess
import sys
from pathlib import Path

import pytest

from cerpe.runfolder.layout import LOCK_FILE
from cerpe.runfolder.lock import RunBusy, RunLock

# Ctrl-C raises KeyboardInterrupt in the holder even when it was started with SIGINT ignored (a background
# job of a non-interactive shell, as some CI runners start their commands)
HOLD = ("import signal, sys; from cerpe.runfolder.lock import RunLock\n"
        "signal.signal(signal.SIGINT, signal.default_int_handler)\n"
        "with RunLock(sys.argv[1]):\n"
        "    print('held', flush=True)\n"
        "    sys.stdin.read()\n")


def _holder(out: Path) -> subprocess.Popen:
    """A process that holds ``out``'s lock until its stdin closes (or it is killed)."""
    p = subprocess.Popen([sys.executable, "-c", HOLD, str(out)], stdin=subprocess.PIPE, stdout=subprocess.PIPE,
                         text=True)
    assert p.stdout.readline().strip() == "held"
    return p


def _cerpe_run(manifest: Path, out: Path, *extra: str) -> subprocess.Popen:
    return subprocess.Popen([sys.executable, "-m", "cerpe.cli", "run", str(manifest), "--method", "sift-ransac",
                             "--out", str(out), "--no-progress", *extra], stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True, env={**os.environ, "PYTHONUNBUFFERED": "1"})


@pytest.fixture()
def manifest(tmp_path: Path) -> Path:
    m = tmp_path / "toy.yaml"  # never loaded while the folder is busy
    m.write_text("name: toy\nadapter: mocap\ndata_root: nowhere\nencounters: []\n")
    return m


def test_a_busy_folder_stops_a_second_run_at_once_naming_the_holder(tmp_path, manifest):
    out = tmp_path / "run"
    holder = _holder(out)
    try:
        second = _cerpe_run(manifest, out)
        _, err = second.communicate(timeout=120)
        assert second.returncode == 2
        lines = err.strip().splitlines()
        assert len(lines) == 1 and "busy" in lines[0] and str(out) in lines[0]
        assert f"pid {holder.pid}" in lines[0] and "--wait" in lines[0]
    finally:
        holder.stdin.close()
        holder.wait(timeout=60)


def test_wait_starts_when_the_holder_is_done(tmp_path, manifest):
    out = tmp_path / "run"
    holder = _holder(out)
    waiter = _cerpe_run(manifest, out, "--wait")
    try:
        line = waiter.stderr.readline()
        while line and "waiting" not in line:
            line = waiter.stderr.readline()
        assert "waiting" in line and waiter.poll() is None  # it waits rather than stopping
    finally:
        holder.stdin.close()
        holder.wait(timeout=60)
    _, err = waiter.communicate(timeout=120)
    # past the lock it read the (unusable) manifest: its own error, not a busy folder
    assert waiter.returncode == 2 and "busy" not in err and "toy.yaml" in err


@pytest.mark.parametrize("how", [signal.SIGINT, signal.SIGKILL])
def test_the_lock_goes_with_its_process(tmp_path, how):
    out = tmp_path / "run"
    holder = _holder(out)
    with pytest.raises(RunBusy, match=f"pid {holder.pid}"):
        RunLock(out).acquire()
    holder.send_signal(how)  # Ctrl-C, or a crash the process cannot clean up after
    holder.wait(timeout=60)
    with RunLock(out) as lock:
        assert lock.held and f"pid {os.getpid()}" in (out / LOCK_FILE).read_text()


def test_one_process_twice_is_busy_too_and_an_empty_folder_it_made_goes(tmp_path):
    out = tmp_path / "new" / "run"
    with RunLock(out):
        with pytest.raises(RunBusy, match="is busy"):
            RunLock(out).acquire()
    assert not out.exists()  # nothing was written: the folder the lock made is removed
    (out / "enc0").mkdir(parents=True)
    with RunLock(out):
        pass
    assert (out / "enc0").is_dir() and (out / LOCK_FILE).is_file()  # a folder with content stays

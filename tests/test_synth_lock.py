"""Two processes asking for the same synthetic suite at once (two robots started on one host from
one manifest with an empty cache): the second waits for the first and reuses its result."""
from __future__ import annotations

import fcntl
import os
import subprocess
import sys
import threading
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
CONF = {"seed": 1, "n_encounters": 2, "n_frames": 4, "fps": 2.0, "size": (64, 48), "n_robots": 2}
SCRIPT = f"""
import logging, sys
logging.basicConfig(level=logging.INFO, format="%(message)s")
from cerpe.synth import generate_suite
print(generate_suite("indoor-team", sys.argv[1], {CONF!r}, progress=False))
"""


WAITING = "another process is rendering it; waiting"


def _start(out: Path) -> tuple[subprocess.Popen, list[str], threading.Thread]:
    """The process, the lines of its log as they come, and the thread reading them."""
    env = {**os.environ, "PYTHONPATH": str(ROOT), "OMP_NUM_THREADS": "1"}
    p = subprocess.Popen([sys.executable, "-c", SCRIPT, str(out)], stdout=subprocess.PIPE,
                         stderr=subprocess.PIPE, text=True, env=env)
    lines: list[str] = []
    reader = threading.Thread(target=lambda: lines.extend(iter(p.stderr.readline, "")), daemon=True)
    reader.start()
    return p, lines, reader


def test_two_processes_render_one_suite_once(tmp_path: Path) -> None:
    out = tmp_path / "cache" / "indoor-team-seed1"
    out.parent.mkdir()
    # hold the lock while both start, so that both surely ask for the suite while it is being made
    with open(out.with_name(f".{out.name}.lock"), "a+") as fh:
        fcntl.flock(fh, fcntl.LOCK_EX)
        procs = [_start(out), _start(out)]
        deadline = time.time() + 120
        while time.time() < deadline and not all(p.poll() is not None or any(WAITING in ln for ln in lines)
                                                 for p, lines, _ in procs):
            time.sleep(0.1)
        fcntl.flock(fh, fcntl.LOCK_UN)
    results = []
    for p, lines, reader in procs:
        rc = p.wait(timeout=300)
        reader.join(timeout=60)
        results.append((rc, p.stdout.read(), "".join(lines)))
    for rc, stdout, stderr in results:
        assert rc == 0, stderr
        assert stdout.strip() == str(out / "manifest.yaml")
        assert "Traceback" not in stderr
    logs = [stderr for _, _, stderr in results]
    assert all(WAITING in e for e in logs)  # both met the lock held by the test
    assert sum("nothing rendered" in e for e in logs) == 1  # one rendered, the other reused its suite
    assert (out / "meta.json").is_file() and not out.with_name(f".{out.name}.partial").exists()
    assert len(list(out.glob("*/r0/rgb/*.png"))) == 2 * 4

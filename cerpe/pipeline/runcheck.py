"""Is a cached run folder current? The one check that ``cerpe paper``, ``cerpe dev``, the Pareto
settings and the message-loss sweep use before reusing a run instead of running it again.

Reads ``run.json`` and the encounters' ``DONE.json`` only (see :mod:`cerpe.pipeline.run` for the
layout); builds no model and runs nothing.
"""
from __future__ import annotations

import json
from pathlib import Path

from ..atomicio import AtomicIOError, read_json
from .methods import CERPE_METHODS
from .provenance import code_hash, file_digest


def run_is_current(out: Path, manifest: Path, method: str, preset: str, overrides: dict | None = None) -> bool:
    """Cheap check that a cached run folder is finished and matches the current code and manifest.

    Compares ``run.json``'s code hash, manifest digest, preset and configuration overrides
    (``cerpe run --set``; none is none) and requires a ``DONE.json`` with the run's
    fingerprint for every encounter; builds no model.
    """
    try:
        meta = read_json(out / "run.json", "run.json")
        cfg = meta["config"]
        if cfg.get("code") != code_hash(method) or cfg.get("manifest_sha") != file_digest(manifest):
            return False
        if (cfg.get("overrides") or None) != (json.loads(json.dumps(overrides)) if overrides else None):
            return False
        if method in CERPE_METHODS and cfg.get("profile") != preset:
            return False
        return all(read_json(out / enc / "DONE.json", "DONE.json").get("fingerprint") == meta["fingerprint"]
                   for enc in cfg.get("encounters", []))
    except (AtomicIOError, KeyError, OSError):
        return False

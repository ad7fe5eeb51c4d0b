"""Is a cached run folder current? The one check that ``cerpe paper``, ``cerpe dev``, the Pareto
settings and the message-loss sweep make before reusing a run instead of running it again.

Reads ``run.json`` and the encounters' ``DONE.json`` only; builds no model and runs nothing.
"""
from __future__ import annotations

import json
from pathlib import Path
from typing import Any, Mapping, Sequence

from ..atomicio import AtomicIOError, read_json
from ..methods import CERPE_METHODS
from .layout import DONE_JSON, RUN_FORMAT, RUN_JSON
from .provenance import code_hash, file_digest


def run_is_current(out: Path, manifest: Path, method: str, preset: str = "paper",
                   sets: Mapping[str, Any] | None = None, encounters: Sequence[str] | None = None) -> bool:
    """Cheap check that a cached run folder is finished and matches the current code and manifest.

    Compares ``run.json``'s run format, code hash, manifest digest, and for the cerpe methods the
    preset and ``--set`` knobs (none is none); with ``encounters``, the run must be of exactly those
    (a run of a subset, as the Pareto settings make). Requires a ``DONE.json`` with the run's
    fingerprint for every encounter; builds no model.
    """
    try:
        meta = read_json(Path(out) / RUN_JSON, RUN_JSON)
        cfg = meta["config"]
        if (cfg.get("format") != RUN_FORMAT or cfg.get("code") != code_hash(method)
                or cfg.get("manifest_sha") != file_digest(manifest)):
            return False
        if (cfg.get("sets") or None) != (json.loads(json.dumps(dict(sets))) if sets else None):
            return False
        if method in CERPE_METHODS and cfg.get("preset") != preset:
            return False
        if encounters is not None and list(cfg.get("encounters", [])) != list(encounters):
            return False
        return all(read_json(Path(out) / enc / DONE_JSON, DONE_JSON).get("fingerprint") == meta["fingerprint"]
                   for enc in cfg.get("encounters", []))
    except (AtomicIOError, KeyError, OSError):
        return False

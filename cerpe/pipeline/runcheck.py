"""Is a cached run folder current? The one check that ``cerpe paper``, ``cerpe dev``, the Pareto
settings and the message-loss sweep use before reusing a run instead of running it again.

Reads ``run.json`` and the encounters' ``DONE.json`` only (see :mod:`cerpe.pipeline.run` for the
layout); builds no model and runs nothing.
"""
from __future__ import annotations

import json
from pathlib import Path
from typing import Any, Mapping

from ..atomicio import AtomicIOError, read_json
from .methods import CERPE_METHODS
from .provenance import code_hash, file_digest


def run_is_current(out: Path, manifest: Path, method: str, preset: str = "paper",
                   sets: Mapping[str, Any] | None = None) -> bool:
    """Cheap check that a cached run folder is finished and matches the current code and manifest.

    Compares ``run.json``'s run format, code hash, manifest digest, and for the cerpe methods the
    preset and ``--set`` knobs (none is none), and requires a ``DONE.json`` with the run's
    fingerprint for every encounter; builds no model.
    """
    from .run import RUN_FORMAT

    try:
        meta = read_json(out / "run.json", "run.json")
        cfg = meta["config"]
        if (cfg.get("format") != RUN_FORMAT or cfg.get("code") != code_hash(method)
                or cfg.get("manifest_sha") != file_digest(manifest)):
            return False
        if (cfg.get("sets") or None) != (json.loads(json.dumps(dict(sets))) if sets else None):
            return False
        if method in CERPE_METHODS and cfg.get("preset") != preset:
            return False
        return all(read_json(out / enc / "DONE.json", "DONE.json").get("fingerprint") == meta["fingerprint"]
                   for enc in cfg.get("encounters", []))
    except (AtomicIOError, KeyError, OSError):
        return False


def gate_tau(meta: Mapping[str, Any]) -> float | None:
    """The gate threshold a CERPE run used, from its ``run.json`` (None for a baseline's)."""
    tau = (meta.get("config", {}).get("method_config", {}).get("tree", {}).get("gate", {}).get("tau"))
    return None if tau is None else float(tau)


def timing_note(meta: Mapping[str, Any], cpu_count: int | None) -> str:
    """How a run's timings were taken, from the command its ``run.json`` recorded: ``cerpe paper --jobs N``
    (N > 1; 2 by default) ran N runs side by side on the machine's cores, so their timings are contended."""
    tokens = str(meta.get("command", "")).split()
    if "paper" not in tokens:
        return "timed while the runs were made, not by `cerpe bench`"
    rest = tokens[tokens.index("paper") + 1:]
    jobs = int(rest[rest.index("--jobs") + 1]) if "--jobs" in rest[:-1] else 2  # `cerpe paper`'s default
    if "fixture" in rest or jobs <= 1:  # the fixture suite runs one run at a time whatever --jobs says
        return "timed during `cerpe paper`, one run at a time"
    return (f"contended: timed during `cerpe paper --jobs {jobs}`, {jobs} runs side by side on "
            f"{cpu_count or '?'} CPU cores")

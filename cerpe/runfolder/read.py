"""Reading run folders: :func:`load_run` -> :class:`Run` (``run.json`` and every encounter's rows).

A folder is read only when every encounter of its configuration finished under the fingerprint
of its ``run.json`` (else :class:`EvalError` names the file and why); a corrupt or half-written
file is named, never a traceback. Reading takes no lock: a finished encounter's files are
complete (``DONE.json`` is written last).
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any, Mapping, Sequence

import pandas as pd

from ..atomicio import AtomicIOError, read_json
from ..errors import CerpeError
from .layout import DONE_JSON, FRAME_KEY, PEER_OVERLAP_CSV, REQUIRED_STEP_COLS, ROBOTS_CSV, RUN_JSON, STEPS_CSV


class EvalError(CerpeError, ValueError):
    """Unusable run folder (unfinished, corrupt, mixed configurations)."""


@dataclass
class Run:
    """One run folder, loaded.

    Attributes:
        path: the folder.
        meta: ``run.json``.
        steps: all encounters' ``steps.csv`` rows, concatenated.
        robots: all encounters' ``robots.csv`` rows, concatenated.
    """

    path: Path
    meta: dict
    steps: pd.DataFrame
    robots: pd.DataFrame
    peer_overlap: pd.DataFrame | None = None  # online robot: ``overlap_gt`` of its peers' rows about it
    paths: tuple[Path, ...] = ()  # an online team: every robot's folder

    @property
    def method(self) -> str:
        return self.meta["method"]

    @property
    def setting(self) -> str:
        return self.meta["setting"]

    @property
    def fingerprint(self) -> str:
        return self.meta["fingerprint"]

    @property
    def metric_scale(self) -> bool:
        return bool(self.meta.get("metric_scale", False))

    @property
    def every(self) -> int:
        return int(self.meta.get("config", {}).get("evaluation_every", 1))


def _read_csv(path: Path, required: Sequence[str] = ()) -> pd.DataFrame:
    try:
        df = pd.read_csv(path)
    except FileNotFoundError:
        raise EvalError(f"missing results file: {path}") from None
    except (pd.errors.ParserError, pd.errors.EmptyDataError, UnicodeDecodeError) as exc:
        raise EvalError(f"corrupt or half-written results file {path}: {exc}") from None
    except OSError as exc:
        raise EvalError(f"cannot read results file {path}: {exc.strerror or exc}") from None
    missing = [c for c in required if c not in df.columns]
    if missing:
        raise EvalError(f"{path}: missing columns {missing} (half-written or from another version?)")
    return df


def load_run(path: Path | str, allow_partial: bool = False) -> Run:
    """Load a run folder; every encounter of its configuration must be finished.

    Raises :class:`EvalError` naming the file for a missing/corrupt ``run.json``,
    an unfinished encounter (unless ``allow_partial``), an encounter finished
    under another fingerprint, or a corrupt CSV.
    """
    path = Path(path)
    if path.exists() and not path.is_dir():
        raise EvalError(f"{path}: a file, not a run folder (pass the folder `cerpe run --out` wrote)")
    if not path.exists():
        raise EvalError(f"{path}: run folder not found (no {path / 'run.json'})")
    try:
        meta = read_json(path / RUN_JSON, RUN_JSON)
    except AtomicIOError as exc:
        raise EvalError(f"{path}: not a run folder ({exc})") from None
    for k in ("method", "setting", "fingerprint", "config"):
        if k not in meta:
            raise EvalError(f"{path / 'run.json'}: missing field {k!r}")
    if not isinstance(meta["config"], dict):
        raise EvalError(f"{path / 'run.json'}: field 'config' is not a mapping")
    steps, robots, peers = [], [], []
    for enc in meta["config"].get("encounters", []):
        done = path / enc / DONE_JSON
        if not done.exists():
            if allow_partial:
                continue
            raise EvalError(f"{path}: encounter {enc!r} is not finished (no DONE.json); "
                            f"rerun `cerpe run` with the same arguments to resume")
        try:
            d = read_json(done, DONE_JSON)
        except AtomicIOError as exc:
            raise EvalError(str(exc)) from None
        if d.get("fingerprint") != meta["fingerprint"]:
            raise EvalError(f"{done}: encounter finished under configuration {d.get('fingerprint')}, "
                            f"run.json says {meta['fingerprint']}: refusing to mix configurations")
        s = _read_csv(path / enc / STEPS_CSV, REQUIRED_STEP_COLS)
        if "n_pair_rows" in d and len(s) != int(d["n_pair_rows"]):
            raise EvalError(f"{path / enc / STEPS_CSV}: {len(s)} rows, DONE.json says {d['n_pair_rows']}")
        steps.append(s)
        robots.append(_read_csv(path / enc / ROBOTS_CSV, ("encounter", "step", "robot")))
        if (path / enc / PEER_OVERLAP_CSV).is_file():
            peers.append(_read_csv(path / enc / PEER_OVERLAP_CSV, (*FRAME_KEY, "overlap_gt")))
    if not steps:
        raise EvalError(f"{path}: no finished encounter")
    sdf = pd.concat(steps, ignore_index=True)
    sdf["encounter"] = sdf["encounter"].astype(str)
    rdf = pd.concat(robots, ignore_index=True)
    rdf["encounter"] = rdf["encounter"].astype(str)
    pdf = pd.concat(peers, ignore_index=True).astype({"encounter": str}) if peers else None
    return Run(path, meta, sdf, rdf, pdf, (path,))


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
    if jobs <= 1:
        return "timed during `cerpe paper`, one run at a time"
    return (f"contended: timed during `cerpe paper --jobs {jobs}`, {jobs} runs side by side on "
            f"{cpu_count or '?'} CPU cores")

"""Writing a run folder: ``run.json`` created or checked under the folder's lock, then each encounter's files.

:func:`open_run` is the one place that decides whether a folder may be written: a folder that is
not a run folder is refused; one whose ``run.json`` holds another configuration (its
fingerprint differs: method, configuration, seed, manifest or code) or another run format is
refused with the way to rerun it, unless ``overwrite`` (then it is emptied). A folder of the same
configuration is resumed: its finished encounters (``DONE.json`` with this fingerprint) are
skipped, the others recomputed. :func:`run_encounter_to_folder` runs one encounter's steps and
writes its files, each to a temporary name and renamed, ``DONE.json`` last.
"""
from __future__ import annotations

import logging
import shutil
import sys
import time
from pathlib import Path
from typing import Any, Callable, Iterator, Mapping, Sequence

import numpy as np

from ..atomicio import AtomicIOError, atomic_write_json, atomic_write_text, ensure_dir, read_json
from ..geometry import se3_to_tq_xyzw
from ..records import STAGES, StepResult
from ..tum import format_tum, format_tum_cov
from .layout import DONE_JSON, LOCK_FILE, ROBOTS_CSV, RUN_FORMAT, RUN_JSON, STEPS_CSV, RunError
from .lock import RunLock
from .provenance import fingerprint, git_revision, package_versions

log = logging.getLogger(__name__)

StepSource = Callable[[Any], Iterator[StepResult]]


def check_out(out: Path | str) -> Path:
    """Refuse an ``--out`` that cannot be a run folder (a file, or a folder of something else), before any work."""
    out = Path(out)
    ensure_dir(out, "--out", create=False)
    if out.is_dir() and not (out / RUN_JSON).exists() and any(p.name != LOCK_FILE for p in out.iterdir()):
        raise RunError(f"--out {out}: a folder that is not a run folder (no run.json) and not empty; "
                       f"choose another --out (cerpe never writes into a folder it did not make)")
    return out


class RunFolder:
    """A run folder opened for writing by :func:`open_run`: ``run.json`` written, the lock held until
    :meth:`close` (a context manager)."""

    def __init__(self, path: Path, fp: str, config: dict, lock: RunLock) -> None:
        self.path, self.fingerprint, self.config, self.lock = path, fp, config, lock

    def is_done(self, encounter: str) -> bool:
        """Whether ``encounter`` finished under this configuration (``DONE.json`` with this fingerprint)."""
        done = self.path / encounter / DONE_JSON
        if not done.exists():
            return False
        try:
            return read_json(done, DONE_JSON).get("fingerprint") == self.fingerprint
        except AtomicIOError as exc:
            log.warning("%s; recomputing encounter %s", exc, encounter)
            return False

    def todo(self, encounters: Sequence[Any]) -> list[Any]:
        """The encounters (objects with a ``name``) not finished under this configuration."""
        return [e for e in encounters if not self.is_done(e.name)]

    def write_encounter(self, encounter: Any, steps: StepSource, progress: bool = True) -> dict:
        """Run ``encounter`` with ``steps`` into its folder (its old ``DONE.json`` removed first)."""
        enc_dir = self.path / encounter.name
        (enc_dir / DONE_JSON).unlink(missing_ok=True)
        return run_encounter_to_folder(encounter, steps, enc_dir, self.fingerprint, progress=progress)

    def close(self) -> None:
        self.lock.release()

    def __enter__(self) -> "RunFolder":
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def open_run(out: Path | str, config: Mapping[str, Any], record: Mapping[str, Any], *, overwrite: bool = False,
             wait: bool = False, lock: RunLock | None = None) -> RunFolder:
    """Open run folder ``out`` for writing the run of ``config``; returns it locked (close it when done).

    Args:
        config: everything that determines the results (method, configuration, seed, manifest digest,
            encounters, code hash...); ``format`` (:data:`RUN_FORMAT`) is added. Its fingerprint
            names the configuration.
        record: what ``run.json`` records beside it (label, manifest path, seed, setting...).
        overwrite: replace a folder of another configuration or run format instead of refusing.
        wait: wait for another process writing ``out`` instead of raising :class:`~cerpe.runfolder.lock.RunBusy`.
        lock: ``out``'s lock, already held by the caller (taken before loading any data); else it is taken here.
    """
    out = check_out(out)
    config = {"format": RUN_FORMAT, **config}
    fp = fingerprint(config)
    ensure_dir(out, "--out")
    lock = (lock or RunLock(out, wait=wait)).acquire()
    try:
        check_out(out)  # the holder may have left something else behind
        run_json = out / RUN_JSON
        if run_json.exists():
            old = read_json(run_json, RUN_JSON)
            fmt = old.get("config", {}).get("format")
            if fmt != RUN_FORMAT and not overwrite:
                raise RunError(f"{run_json}: written by another version of cerpe (run format {fmt}, this one "
                               f"writes {RUN_FORMAT}); rerun with --overwrite to replace it, or choose another --out")
            if old.get("fingerprint") != fp:
                if not overwrite:
                    diff = sorted(k for k in config if old.get("config", {}).get(k) != config[k])
                    raise RunError(
                        f"{run_json}: run folder belongs to another configuration (fingerprint "
                        f"{old.get('fingerprint')} != {fp}; differs in {diff}); use another --out or --overwrite")
                log.warning("replacing run folder %s (configuration changed)", out)
                _empty(out)
        for stale in out.rglob(".*.tmp"):  # leftovers of an interrupted atomic write
            stale.unlink(missing_ok=True)
        atomic_write_json(run_json, {**record, "fingerprint": fp, "config": config,
                                     "package_versions": package_versions(), "git_revision": git_revision(),
                                     "command": " ".join(sys.argv)})
    except BaseException:
        lock.release()
        raise
    return RunFolder(out, fp, config, lock)


def _empty(folder: Path) -> None:
    """Remove everything in ``folder`` but its lock file (which this process holds)."""
    for p in folder.iterdir():
        if p.name == LOCK_FILE:
            continue
        if p.is_dir() and not p.is_symlink():
            shutil.rmtree(p)
        else:
            p.unlink()


# --------------------------------------------------------------------------- encounter -> files
def gt_cols(T: np.ndarray | None) -> dict[str, float]:
    """The ``gt_tx .. gt_qw`` columns of ground truth ``T`` (NaN where none or not finite)."""
    names = ("tx", "ty", "tz", "qx", "qy", "qz", "qw")
    if T is None or not np.all(np.isfinite(T)):
        return {f"gt_{n}": float("nan") for n in names}
    t, q = se3_to_tq_xyzw(T)
    return {f"gt_{n}": float(v) for n, v in zip(names, [*t, *q])}


def csv_text(rows: list[dict]) -> str:
    """Rows as CSV: values to 9 significant digits, ``stamp_s`` to the nanosecond (an epoch stamp has
    10 digits before the point: ``%.9g`` kept it to 10 s)."""
    import pandas as pd

    df = pd.DataFrame(rows)
    if "stamp_s" in df:
        stamps = pd.to_numeric(df["stamp_s"], errors="coerce").to_numpy(float)
        df["stamp_s"] = [f"{v:.9f}" if np.isfinite(v) else "" for v in stamps]
    return df.to_csv(index=False, float_format="%.9g")


def run_encounter_to_folder(encounter: Any, steps: StepSource, enc_dir: Path, fp: str,
                            progress: bool = True) -> dict:
    """Run one encounter and write its files; DONE.json last. Returns DONE's content.

    An encounter whose ``n_steps`` is None is open-ended (a robot online by stamps: its frames are
    those it took, until its input ended); otherwise ``steps`` must give every step."""
    from tqdm import tqdm

    idx = {r.robot_id: k for k, r in enumerate(encounter.robots)}
    step_rows: list[dict] = []
    robot_rows: list[dict] = []
    est: dict[tuple[str, str], list[tuple[float, np.ndarray, np.ndarray | None, np.ndarray | None]]] = {}
    odo: dict[str, list[tuple[float, np.ndarray]]] = {r.robot_id: [] for r in encounter.robots}
    t0 = time.perf_counter()
    n_steps = 0
    bar = tqdm(total=getattr(encounter, "n_steps", None), desc=f"{encounter.name}", unit="step", disable=not progress,
               leave=False, dynamic_ncols=True)
    try:
        for res in steps(encounter):
            t = res.step
            rob_by_id = {rr.robot: rr for rr in res.robots}
            for rr in res.robots:
                robot_rows.append({"encounter": encounter.name, **rr.as_row()})
                if rr.T_odom_cam is not None and np.all(np.isfinite(rr.T_odom_cam)):
                    odo[rr.robot].append((rr.stamp_s, rr.T_odom_cam))
            for pr in res.pairs:
                i, j = idx[pr.ego], idx[pr.other]
                T_gt = encounter.gt_T_cj_ci(t, i, j)
                row = {"encounter": encounter.name, **pr.as_row(), **gt_cols(T_gt)}
                row["overlap_gt"] = (float(encounter.overlap[t, i, j]) if encounter.overlap is not None
                                     else float("nan"))
                row["view_angle_gt"] = encounter.gt_viewing_angle(t, i, j)
                rr = rob_by_id.get(pr.ego)
                for s in STAGES:  # the ego robot's stage timings at this step
                    row[f"t_{s}_s"] = float(rr.timings_s.get(s, 0.0)) if rr else float("nan")
                step_rows.append(row)
                if pr.T_cj_ci is not None and np.all(np.isfinite(pr.T_cj_ci)):
                    est.setdefault((pr.ego, pr.other), []).append((pr.stamp_s, pr.T_cj_ci, T_gt, pr.cov))
            n_steps += 1
            bar.update(1)
    finally:
        bar.close()
    wall = time.perf_counter() - t0
    if encounter.n_steps is not None and n_steps != encounter.n_steps:
        raise RunError(f"encounter {encounter.name}: method produced {n_steps} steps for {encounter.n_steps}")
    enc_dir.mkdir(parents=True, exist_ok=True)
    atomic_write_text(enc_dir / STEPS_CSV, csv_text(step_rows))
    atomic_write_text(enc_dir / ROBOTS_CSV, csv_text(robot_rows))
    for (a, b), items in est.items():
        stamps = np.array([s for s, _, _, _ in items])
        poses = np.array([T for _, T, _, _ in items])
        atomic_write_text(enc_dir / "poses" / f"{a}__{b}.tum", format_tum(stamps, poses))
        if any(C is not None for _, _, _, C in items):  # methods with a covariance (cerpe-graph)
            cov = np.array([np.full((6, 6), np.nan) if C is None else C for _, _, _, C in items])
            atomic_write_text(enc_dir / "poses" / f"{a}__{b}.cov", format_tum_cov(stamps, poses, cov))
        with_gt = [(s, G) for s, _, G, _ in items if G is not None]
        if with_gt:
            atomic_write_text(enc_dir / "poses" / f"{a}__{b}.gt.tum",
                              format_tum(np.array([s for s, _ in with_gt]), np.array([G for _, G in with_gt])))
    for rid, items in odo.items():
        if items:
            atomic_write_text(enc_dir / "odometry" / f"{rid}.tum",
                              format_tum(np.array([s for s, _ in items]), np.array([T for _, T in items])))
    done = {"encounter": encounter.name, "n_steps": n_steps, "n_pair_rows": len(step_rows),
            "wall_time_s": wall, "fingerprint": fp, "finished_at": time.strftime("%Y-%m-%dT%H:%M:%S")}
    atomic_write_json(enc_dir / DONE_JSON, done)
    return done

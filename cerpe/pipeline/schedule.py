"""``cerpe paper``'s runs as independent jobs on a pool of worker processes.

A job is one unit that must stay in one process: the three CERPE methods of a
setting (they are views of ONE shared pass, see :mod:`cerpe.pipeline.run`), one
per-frame baseline, one Pareto setting (:mod:`cerpe.pipeline.pareto`), or the
message-loss sweep (:mod:`cerpe.pipeline.message_loss`, which reuses the lossless
runs of its setting, so it waits for them). Each job writes its own run folders
exactly as a run in the main process would (seeded, fingerprinted, resumable), so
the tables do not depend on the number of workers; only the wall time does. Every process
runs torch on :func:`cerpe.threads.torch_threads` intra-op threads (1 unless ``CERPE_THREADS``),
so N workers use N cores without oversubscribing them (two ALIKED runs of the SUN3D dev set
side by side on 2 cores: 133 s at 2 threads per worker, 125 s at 1).

Jobs go to free workers longest first (a fixed estimate per kind, times the setting's
robot-steps), each as soon as the jobs it waits for have finished. A job that fails
returns one error line naming the setting and what failed; the others go on.
"""
from __future__ import annotations

import dataclasses
import logging
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

from ..errors import CerpeError
from .methods import BASELINE_METHODS, CERPE_METHODS

log = logging.getLogger(__name__)

#: seconds per robot-step of each kind of job on the reference 2-core machine (make paper of 26e4f7e):
#: only the order of the hand-out depends on them
COST_PER_STEP_S: dict[str, float] = {"cerpe": 0.55, "aliked-lightglue": 0.45, "sift-ransac": 0.1,
                                     "pareto": 0.5, "message-loss": 1.2}


class ScheduleError(CerpeError):
    """A job list that cannot run (a job waiting for one that does not exist)."""


@dataclasses.dataclass(frozen=True)
class Job:
    """One unit of work: ``fn(*args)`` returns ``""`` or an error line; ``after`` names jobs it waits for."""

    name: str
    fn: Callable[..., str]
    args: tuple
    cost_s: float = 1.0
    after: tuple[str, ...] = ()
    outputs: tuple[tuple[str, str], ...] = ()  # (setting, method) run folders the job makes


# --------------------------------------------------------------------------- jobs (module level: picklable)
def methods_job(manifest: Path, methods: Sequence[str], runs_root: Path, sets: dict) -> str:
    """Every method of ``methods`` on one setting, one after another in this process (CERPE's share a pass)."""
    from .methods import CERPE_METHODS
    from .run import load_manifest_setting, run_method

    try:
        setting = load_manifest_setting(manifest)
        for m in methods:
            run_method(manifest, m, Path(runs_root) / setting.name / m, sets=sets if m in CERPE_METHODS else None,
                       overwrite=True, progress=False, setting=setting)
    except CerpeError as exc:
        return str(exc)
    return ""


def load_job(manifest: Path) -> str:
    """Load one setting (a synthetic one is rendered into its cache when missing; the next load reads it)."""
    from ..datasets import ManifestError, load_setting

    try:
        load_setting(manifest)
    except ManifestError as exc:
        return str(exc)
    return ""


def pareto_job(name: str, manifest: Path, runs_root: Path, sets: dict, scheme: str, n_encounters: int | None) -> str:
    """One Pareto preset on one synthetic setting (:func:`cerpe.pipeline.pareto.scheme_runs`)."""
    from .pareto import scheme_runs

    _, errors = scheme_runs([(name, manifest, None)], runs_root, knob_sets=sets, schemes=(scheme,),
                            n_encounters=n_encounters, build=True, progress=False)
    return "; ".join(errors)


def loss_job(conf: dict, paths: dict) -> str:
    """The message-loss sweep (:func:`cerpe.pipeline.message_loss.main`)."""
    from .message_loss import main

    try:
        main(conf, paths)
    except CerpeError as exc:
        return str(exc)
    return ""


# --------------------------------------------------------------------------- make paper's job list
def paper_jobs(ctx: Any, run_is_current: Callable[..., bool]) -> list[Job]:
    """Every run of a :class:`~cerpe.pipeline.paper.PaperContext` that is not current, as jobs.

    ``ctx.run_dirs`` must list the method runs (``paper.context(build=False)``); its
    settings must be loaded (``validate=True``) for the Pareto settings' encounters.
    """
    from . import message_loss, pareto

    jobs: list[Job] = []
    for e in ctx.ok_settings:
        steps = _robot_steps(e.setting.encounters) if e.setting is not None else 100
        stale = [m for (s, m), out in ctx.run_dirs.items()
                 if s == e.name and not run_is_current(out, e.run_manifest, m, sets=ctx.sets_of(m))]
        ours = tuple(m for m in CERPE_METHODS if m in stale)
        if ours:
            jobs.append(Job(f"{e.name}/{'+'.join(ours)}", methods_job, (e.run_manifest, ours, ctx.runs_root,
                                                                       ctx.sets),
                            COST_PER_STEP_S["cerpe"] * steps, outputs=tuple((e.name, m) for m in ours)))
        for m in (m for m in BASELINE_METHODS if m in stale):
            jobs.append(Job(f"{e.name}/{m}", methods_job, (e.run_manifest, (m,), ctx.runs_root, ctx.sets),
                            COST_PER_STEP_S[m] * steps, outputs=((e.name, m),)))
        if not e.world or e.setting is None:  # the Pareto settings run on the synthetic settings only
            continue
        encs = e.setting.encounters[: pareto.N_ENCOUNTERS]
        sub_steps = _robot_steps(encs)
        for scheme in pareto.PARETO_PRESETS:
            path = pareto.run_dir(ctx.runs_root, e.name, scheme)
            if not pareto.is_current(path, e.run_manifest, scheme, ctx.sets, [enc.name for enc in encs]):
                jobs.append(Job(f"{e.name}/pareto-{scheme}", pareto_job,
                                (e.name, e.run_manifest, ctx.runs_root, ctx.sets, scheme, pareto.N_ENCOUNTERS),
                                COST_PER_STEP_S["pareto"] * sub_steps))
    try:
        conf, paths = message_loss.context_paths(ctx)
    except message_loss.MessageLossError:
        return jobs  # no such setting in this profile: the notebook says so
    lossless = {(conf["setting"], m) for m in conf["methods"]}  # its loss-0 point: reused when current
    runs = len(conf["loss_seeds"]) * len(conf["losses"])
    jobs.append(Job("message-loss", loss_job, (conf, paths), COST_PER_STEP_S["message-loss"] * 2 * runs
                    * int(conf["max_steps"] or 50), after=tuple(j.name for j in jobs if lossless & set(j.outputs))))
    return jobs


def _robot_steps(encounters: Sequence[Any]) -> int:
    return sum(len(enc.robots) * len(enc.robots[0]) for enc in encounters)


# --------------------------------------------------------------------------- the pool
def run_jobs(jobs: Sequence[Job], workers: int = 2, progress: bool = True) -> list[tuple[Job, str]]:
    """Run ``jobs`` on ``workers`` spawned processes; returns ``(job, error)`` per failed job.

    A job runs once every job of its ``after`` has finished (failed ones too: a
    dependent job then makes what it needs itself, as it would alone).
    """
    import multiprocessing
    from concurrent.futures import FIRST_COMPLETED, ProcessPoolExecutor, wait

    from tqdm import tqdm

    names = {j.name for j in jobs}
    for j in jobs:
        missing = [a for a in j.after if a not in names]
        if missing:
            raise ScheduleError(f"job {j.name}: waits for {missing}, which are not jobs ({sorted(names)})")
    waiting = sorted(jobs, key=lambda j: -j.cost_s)
    finished: set[str] = set()
    running: dict[Any, tuple[Job, float]] = {}
    failed: list[tuple[Job, str]] = []
    bar = tqdm(total=len(jobs), desc="cerpe paper runs", unit="job", disable=not progress)
    with ProcessPoolExecutor(max(1, int(workers)), mp_context=multiprocessing.get_context("spawn")) as pool:
        while waiting or running:
            for j in [j for j in waiting if all(a in finished for a in j.after)][:max(1, int(workers)) - len(running)]:
                waiting.remove(j)
                running[pool.submit(j.fn, *j.args)] = (j, time.perf_counter())
                log.info("job %s: started", j.name)
            if not running:
                raise ScheduleError(f"jobs {[j.name for j in waiting]} wait for each other")
            done, _ = wait(list(running), return_when=FIRST_COMPLETED)
            for fut in done:
                j, t0 = running.pop(fut)
                try:
                    err = fut.result()
                except Exception as exc:  # the worker died (killed, out of memory): say which job
                    err = f"the worker process failed: {type(exc).__name__}: {exc}"
                finished.add(j.name)
                bar.update(1)
                bar.set_postfix_str(j.name)
                log.info("job %s: %s in %.0f s", j.name, "failed" if err else "done", time.perf_counter() - t0)
                if err:
                    failed.append((j, err))
    bar.close()
    return failed

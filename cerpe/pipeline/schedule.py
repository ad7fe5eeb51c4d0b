"""``cerpe paper``'s runs as independent jobs on an executor: this process, worker processes, or a Dask cluster.

A job is one unit that must stay in one process: the CERPE methods of a setting (views of ONE
pass per encounter, :func:`cerpe.pipeline.run.run_methods`), one per-frame baseline, one Pareto
setting (:mod:`cerpe.pipeline.pareto`), or the message-loss sweep (:mod:`cerpe.pipeline.message_loss`,
which reuses the lossless runs of its setting, so it waits for them). Each job writes its own run
folders exactly as a run in the main process would (seeded, fingerprinted, resumable, locked), so
the tables do not depend on where or on how many workers the jobs ran; only the wall time does.
Every process runs torch on :func:`cerpe.threads.torch_threads` intra-op threads (1 unless
``CERPE_THREADS``), so N workers use N cores without oversubscribing them (two ALIKED runs of the
SUN3D dev set side by side on 2 cores: 133 s at 2 threads per worker, 125 s at 1).

Jobs go to free workers longest first (a fixed estimate per kind, times the setting's
robot-steps), each as soon as the jobs it waits for have finished. A job that fails
returns one error line naming the setting and what failed; the others go on.

Where they run (:func:`open_pool`): one worker, this process, one job after the other; N workers,
a ``concurrent.futures.ProcessPoolExecutor`` of N spawned processes; a Dask scheduler address
(``cerpe paper --scheduler tcp://HOST:8786``), the same jobs through ``dask.distributed``'s
executor onto its workers, one job per worker thread (start them with ``dask worker
tcp://HOST:8786 --nthreads 1``). Dask workers must see the same checkout and ``build/`` folder
at the same paths (a shared file system): a job names its manifest and run folders by path.
Dask is optional: ``pip install -e '.[dask]'`` (``make setup`` installs it).
"""
from __future__ import annotations

import concurrent.futures as cf
import contextlib
import dataclasses
import logging
import time
from collections.abc import Callable, Iterator, Sequence
from pathlib import Path
from typing import Any

from ..errors import CerpeError
from ..methods import BASELINE_METHODS, CERPE_METHODS
from ..runfolder.current import run_is_current as _run_is_current

log = logging.getLogger(__name__)

#: seconds per robot-step of each kind of job on the reference 2-core machine (make paper of 26e4f7e):
#: only the order of the hand-out depends on them
COST_PER_STEP_S: dict[str, float] = {"cerpe": 0.55, "aliked-lightglue": 0.45, "sift-ransac": 0.1,
                                     "pareto": 0.5, "message-loss": 1.2}


class ScheduleError(CerpeError):
    """A job list that cannot run (a job waiting for one that does not exist), or a scheduler that cannot be used."""


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
def method_groups(methods: Sequence[str]) -> list[tuple[str, ...]]:
    """``methods`` as the units that run together: the cerpe methods as one (they share a pass), each other alone."""
    ours = tuple(m for m in CERPE_METHODS if m in methods)
    return ([ours] if ours else []) + [(m,) for m in methods if m not in CERPE_METHODS]


def methods_job(manifest: Path, methods: Sequence[str], runs_root: Path, sets: dict, setting: Any = None,
                progress: bool = False) -> str:
    """Every method of ``methods`` on one setting into ``runs_root/<setting>/<method>`` (:func:`method_groups`:
    the cerpe methods together, with knobs ``sets``); ``setting``: the loaded setting (loaded when None)."""
    from .run import run_methods
    from .setting import load_manifest_setting

    try:
        setting = setting if setting is not None else load_manifest_setting(manifest)
        for group in method_groups(methods):
            ours = group[0] in CERPE_METHODS
            run_methods(manifest, {m: Path(runs_root) / setting.name / m for m in group}, sets=sets if ours else None,
                        overwrite=True, progress=progress, setting=setting)
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


def pareto_job(name: str, manifest: Path, runs_root: Path, sets: dict, scheme: str, n_encounters: int | None,
               progress: bool = False) -> str:
    """One Pareto preset on one synthetic setting (:func:`cerpe.pipeline.pareto.scheme_runs`)."""
    from .pareto import scheme_runs

    _, errors = scheme_runs([(name, manifest, None)], runs_root, knob_sets=sets, schemes=(scheme,),
                            n_encounters=n_encounters, build=True, progress=progress)
    return "; ".join(errors)


def loss_job(conf: dict, paths: dict, progress: bool = False) -> str:
    """The message-loss sweep (:func:`cerpe.pipeline.message_loss.main`)."""
    from .message_loss import main

    try:
        main(conf, paths, progress=progress)
    except CerpeError as exc:
        return str(exc)
    return ""


# --------------------------------------------------------------------------- make paper's job list
def paper_jobs(ctx: Any, run_is_current: Callable[..., bool] = _run_is_current, progress: bool = False) -> list[Job]:
    """Every run of a :class:`~cerpe.pipeline.paper_context.PaperContext` that is not current, as jobs.

    ``ctx.run_dirs`` must list the method runs (``paper.context(build=False)``); its
    settings must be loaded (``validate=True``) for the Pareto settings' encounters.
    ``run_is_current``: the check of a method's run (:func:`cerpe.runfolder.current.run_is_current`);
    ``progress``: the jobs show progress bars (when they run in this process).
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
                                                                       ctx.sets, None, progress),
                            COST_PER_STEP_S["cerpe"] * steps, outputs=tuple((e.name, m) for m in ours)))
        for m in (m for m in BASELINE_METHODS if m in stale):
            jobs.append(Job(f"{e.name}/{m}", methods_job, (e.run_manifest, (m,), ctx.runs_root, ctx.sets, None, progress),
                            COST_PER_STEP_S[m] * steps, outputs=((e.name, m),)))
        if not e.world or e.setting is None:  # the Pareto settings run on the synthetic settings only
            continue
        encs = e.setting.encounters[: pareto.N_ENCOUNTERS]
        sub_steps = _robot_steps(encs)
        for scheme in pareto.PARETO_PRESETS:
            path = pareto.run_dir(ctx.runs_root, e.name, scheme)
            if not _run_is_current(path, e.run_manifest, "cerpe", scheme, ctx.sets, [enc.name for enc in encs]):
                jobs.append(Job(f"{e.name}/pareto-{scheme}", pareto_job,
                                (e.name, e.run_manifest, ctx.runs_root, ctx.sets, scheme, pareto.N_ENCOUNTERS, progress),
                                COST_PER_STEP_S["pareto"] * sub_steps))
    try:
        conf, paths = message_loss.context_paths(ctx)
    except message_loss.MessageLossError:
        return jobs  # no such setting in this profile: the notebook says so
    lossless = {(conf["setting"], m) for m in conf["methods"]}  # its loss-0 point: reused when current
    runs = len(conf["loss_seeds"]) * len(conf["losses"])
    jobs.append(Job("message-loss", loss_job, (conf, paths, progress), COST_PER_STEP_S["message-loss"] * 2 * runs
                    * int(conf["max_steps"] or 50), after=tuple(j.name for j in jobs if lossless & set(j.outputs))))
    return jobs


def _robot_steps(encounters: Sequence[Any]) -> int:
    return sum(len(enc.robots) * len(enc.robots[0]) for enc in encounters)


# --------------------------------------------------------------------------- where the jobs run
class InlineExecutor(cf.Executor):
    """A ``concurrent.futures`` executor that runs each job in this process when it is submitted."""

    def submit(self, fn: Callable[..., Any], /, *args: Any, **kwargs: Any) -> cf.Future:
        fut: cf.Future = cf.Future()
        try:
            fut.set_result(fn(*args, **kwargs))
        except Exception as exc:  # as a pool's future holds its worker's error
            fut.set_exception(exc)
        return fut


@dataclasses.dataclass
class Pool:
    """An open executor: ``slots`` jobs at a time; ``where``, for the log."""

    executor: cf.Executor
    slots: int
    where: str


DASK_INSTALL = "pip install -e '.[dask]' (make setup installs it)"


def require_dask() -> None:
    """Raise :class:`ScheduleError` saying how to install Dask's distributed scheduler when it is not installed."""
    try:
        import distributed  # noqa: F401
    except ImportError as exc:
        raise ScheduleError(f"--scheduler needs Dask's distributed scheduler, which is not installed here ({exc}); "
                            f"install it: {DASK_INSTALL}") from None


@contextlib.contextmanager
def open_pool(workers: int = 2, scheduler: str | None = None) -> Iterator[Pool]:
    """The executor of ``workers`` processes (1: this process), or of the Dask scheduler at ``scheduler``."""
    if scheduler:
        require_dask()
        from distributed import Client

        try:
            client = Client(scheduler, timeout="30s")
        except (OSError, TimeoutError, ValueError) as exc:
            raise ScheduleError(f"--scheduler {scheduler}: cannot connect to the Dask scheduler: {exc}") from None
        try:
            slots = max(1, sum(client.nthreads().values()))
            yield Pool(client.get_executor(pure=False), slots, f"Dask {scheduler} ({slots} worker threads)")
        finally:
            client.close()
        return
    if int(workers) <= 1:
        yield Pool(InlineExecutor(), 1, "this process")
        return
    import multiprocessing

    with cf.ProcessPoolExecutor(int(workers), mp_context=multiprocessing.get_context("spawn")) as pool:
        yield Pool(pool, int(workers), f"{int(workers)} worker processes")


def run_jobs(jobs: Sequence[Job], workers: int = 2, progress: bool = True, *, pool: Pool | None = None,
             scheduler: str | None = None) -> list[tuple[Job, str]]:
    """Run ``jobs`` on ``pool`` (else one opened from ``workers`` and ``scheduler``, :func:`open_pool`);
    returns ``(job, error)`` per failed job.

    A job runs once every job of its ``after`` has finished (failed ones too: a
    dependent job then makes what it needs itself, as it would alone).
    """
    names = {j.name for j in jobs}
    for j in jobs:
        missing = [a for a in j.after if a not in names]
        if missing:
            raise ScheduleError(f"job {j.name}: waits for {missing}, which are not jobs ({sorted(names)})")
    if pool is None:
        with open_pool(workers, scheduler) as opened:
            return run_jobs(jobs, progress=progress, pool=opened)
    from tqdm import tqdm

    waiting = sorted(jobs, key=lambda j: -j.cost_s)
    finished: set[str] = set()
    running: dict[cf.Future, tuple[Job, float]] = {}
    failed: list[tuple[Job, str]] = []
    bar = tqdm(total=len(jobs), desc="cerpe paper runs", unit="job", disable=not progress or pool.slots == 1)
    while waiting or running:
        for j in [j for j in waiting if all(a in finished for a in j.after)][:pool.slots - len(running)]:
            waiting.remove(j)
            log.info("job %s: started (%s)", j.name, pool.where)
            running[pool.executor.submit(j.fn, *j.args)] = (j, time.perf_counter())
        if not running:
            raise ScheduleError(f"jobs {[j.name for j in waiting]} wait for each other")
        done, _ = cf.wait(list(running), return_when=cf.FIRST_COMPLETED)
        for fut in sorted(done, key=lambda f: running[f][1]):
            j, t0 = running.pop(fut)
            try:
                err = fut.result()
            except Exception as exc:  # the worker died (killed, out of memory) or the job broke: say which job
                err = f"the worker failed: {type(exc).__name__}: {exc}"
            finished.add(j.name)
            bar.update(1)
            bar.set_postfix_str(j.name)
            log.info("job %s: %s in %.0f s", j.name, "failed" if err else "done", time.perf_counter() - t0)
            if err:
                failed.append((j, err))
    bar.close()
    return failed

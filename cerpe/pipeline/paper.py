"""Build every table and figure of the paper (what ``make paper`` runs).

Usage: ``cerpe paper [--models offline|paper] [--suite paper-default|fixture] [--jobs N | --scheduler ADDRESS]``

1. every manifest in ``datasets_manifest/``: enabled ones are loaded (synthetic
   settings are generated on demand with the chosen suite); disabled ones are
   listed in Table I as "not supplied" with the manifest to fill;
2. every method runs on every enabled setting (``cerpe run``; cached in
   ``build/runs/<setting>/<method>/`` and resumed; a run of another
   configuration is replaced); the Pareto settings (:mod:`cerpe.pipeline.pareto`) run
   on the first encounter of each synthetic setting (``build/runs/<setting>/pareto-*``), and the
   message-loss sweep (``build/runs/synthetic-indoor/message-loss``); these runs are jobs on
   ``--jobs`` worker processes, or on a Dask cluster (``--scheduler``; :mod:`cerpe.pipeline.schedule`),
   same results;
3. the notebooks run with papermill into ``build/notebooks/`` and write
   ``tables/`` and ``figures/``. When the inputs' fingerprint (run
   fingerprints, notebooks, evaluation/plotting code, parameters) is unchanged
   and every output exists, the notebooks are not executed again.

``--models`` sets ``backbone.models`` of every CERPE run (``offline``: the stand-ins that run here;
``paper``: VGGT + SALAD/DINOv2 + Metric3Dv2 with user-supplied weights).
``--suite fixture`` is the tiny suite the tests use; it writes to
``build/fixture/{runs,figures,tables}`` and never touches the paper outputs.

The notebooks call the functions this module gathers (:func:`context`, :func:`frames`:
:mod:`cerpe.pipeline.paper_context`; :func:`qualitative_data`, :func:`communication_data`,
:func:`gate_data`, :func:`calibration_data`: :mod:`cerpe.pipeline.figure_data`),
:mod:`cerpe.pipeline.table1` (Table I) and :mod:`cerpe.plotting`; settings: :mod:`cerpe.pipeline.paper_settings`;
the notebooks' execution: :mod:`cerpe.pipeline.notebooks`.
"""
from __future__ import annotations

import argparse
import logging
import sys
import time

from ..methods import UNAVAILABLE
from .figure_data import PAPER_NUMBERS, calibration_data, communication_data, gate_data, qualitative_data  # noqa: F401
from .notebooks import EXPECTED_FIGURES, NOTEBOOK_TABLES, NOTEBOOKS, expected_outputs, run_notebooks  # noqa: F401
from .paper_context import RUN_METHODS, PaperContext, context, frames  # noqa: F401
from .paper_settings import MODELS, ROOT, PaperError, SettingEntry, discover_settings, layout  # noqa: F401
from .schedule import DASK_INSTALL

log = logging.getLogger(__name__)


def build_paper(models: str = "offline", suite: str = "paper-default", force_notebooks: bool = False,
                progress: bool = True, jobs: int = 2, scheduler: str | None = None) -> PaperContext:
    """Every run, then the notebooks. The runs are jobs (:mod:`cerpe.pipeline.schedule`) on ``jobs`` worker
    processes (1: this process), or on the Dask cluster of ``scheduler``; the results are the same."""
    from .pareto import context_runs
    from .schedule import Job, load_job, open_pool, paper_jobs, require_dask, run_jobs

    nb_profile = "fixture" if suite == "fixture" else "paper-default"
    if scheduler:  # one error saying how to install it, before any work
        require_dask()
    if models == "paper":  # one error listing what is missing, before any work
        from ..backbones.paper_profile import require_paper

        require_paper()
    lay = layout(nb_profile, models, ROOT)
    with open_pool(jobs, scheduler) as pool:
        here = pool.slots == 1 and not scheduler  # jobs in this process show their progress bars
        # the synthetic worlds render side by side (an error surfaces when context loads it below)
        synth = [e for e in discover_settings(nb_profile, nb_profile, ROOT / "datasets_manifest", lay["manifests"],
                                              load=False) if e.world and e.status == "ok"]
        run_jobs([Job(f"{e.name}/render", load_job, (e.run_manifest,)) for e in synth], progress=progress, pool=pool)
        ctx = context(nb_profile, models=models, build=False, progress=progress, validate=True)
        t0 = time.perf_counter()
        for job, err in run_jobs(paper_jobs(ctx, progress=progress and here), progress=progress, pool=pool):
            msg = f"{job.name}: {err}"
            log.error(msg)
            ctx.errors.append(msg)
            for key in job.outputs:
                ctx.run_dirs.pop(key, None)
        log.info("runs on %s: %.1f s", pool.where, time.perf_counter() - t0)
    # the Pareto settings on a few encounters (notebook 07 reads them), made by the jobs above
    runs, errors = context_runs(ctx, build=False, progress=progress)
    ctx.extra_runs = sorted({r.path for r in runs if r.path.name.startswith("pareto-")})
    ctx.errors += errors
    run_notebooks(ctx, force=force_notebooks)
    return ctx


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--models", default="offline", choices=MODELS,
                   help="backbone.models of every CERPE run: offline (the stand-ins that run here) or paper "
                        "(VGGT + SALAD/DINOv2 + Metric3Dv2, needs your weights: docs/PAPER_MODELS.md)")
    p.add_argument("--suite", default="paper-default", choices=("paper-default", "fixture"),
                   help="synthetic suite size; fixture writes to build/fixture/ only")
    p.add_argument("--force-notebooks", action="store_true", help="execute the notebooks even if nothing changed")
    p.add_argument("--no-progress", action="store_true", help="no progress bars")
    p.add_argument("--jobs", type=int, default=2, metavar="N",
                   help="worker processes for the runs (default 2, for 2 cores; 1: every run in this process "
                        "with per-encounter progress bars); the tables are the same for any N")
    p.add_argument("--scheduler", default=None, metavar="ADDRESS",
                   help="run the jobs on the Dask cluster of this scheduler instead (e.g. tcp://HOST:8786; "
                        "workers started with `dask worker ADDRESS --nthreads 1`, seeing this checkout and its "
                        "build/ at the same paths); needs the dask extra: " + DASK_INSTALL)


def main(args: argparse.Namespace) -> int:
    t0 = time.perf_counter()
    if args.jobs < 1:
        print(f"cerpe paper: error: --jobs {args.jobs}: at least 1", file=sys.stderr)
        return 2
    ctx = build_paper(args.models, args.suite, args.force_notebooks, progress=not args.no_progress, jobs=args.jobs,
                      scheduler=args.scheduler)
    print(f"tables:    {ctx.tables_dir}")
    print(f"figures:   {ctx.figures_dir}")
    print(f"notebooks: {ctx.notebooks_dir}")
    print(f"runs:      {ctx.runs_root}")
    for e in ctx.settings:
        print(f"  setting {e.name}: {e.status}{' (' + e.detail + ')' if e.detail else ''}")
    for m, why in UNAVAILABLE.items():
        print(f"  method {m}: not available offline ({why})")
    print(f"done in {time.perf_counter() - t0:.1f} s")
    if ctx.errors or any(e.status == "error" for e in ctx.settings):
        for msg in ctx.errors:
            print(f"cerpe paper: error: {msg}", file=sys.stderr)
        return 1
    return 0

"""A notebook profile's runs: :class:`PaperContext` (settings, run folders, output folders) and
:func:`context`, which locates them and, with ``build``, runs the stale ones in this process.

``fixture``: the synthetic fixture suite, runs cached in ``build/fixture/runs``; ``paper-default``:
the paper suite in ``build/runs`` (what ``cerpe paper`` builds, on its scheduler).
"""
from __future__ import annotations

import logging
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Sequence

import pandas as pd

from ..runfolder.current import run_is_current
from .evaluate import EvalError, evaluate_runs
from .paper_settings import MODELS, ROOT, PaperError, SettingEntry, discover_settings, ensure_loaded, layout
from .schedule import method_groups, methods_job

log = logging.getLogger(__name__)

RUN_METHODS: tuple[str, ...] = ("cerpe", "cerpe-wo-em", "cerpe-graph", "sift-ransac", "aliked-lightglue")


@dataclass
class PaperContext:
    profile: str
    suite: str
    models: str
    runs_root: Path
    figures_dir: Path
    tables_dir: Path
    notebooks_dir: Path
    settings: list[SettingEntry] = field(default_factory=list)
    run_dirs: dict[tuple[str, str], Path] = field(default_factory=dict)
    errors: list[str] = field(default_factory=list)
    extra_runs: list[Path] = field(default_factory=list)  # runs beside the methods' (the Pareto settings)

    @property
    def ok_settings(self) -> list[SettingEntry]:
        return [s for s in self.settings if s.status == "ok"]

    @property
    def sets(self) -> dict[str, Any]:
        """The knobs every CERPE run of the context sets besides its preset."""
        return {} if self.models == "offline" else {"backbone.models": self.models}

    def sets_of(self, method: str) -> dict[str, Any] | None:
        """:attr:`sets` for a CERPE method, None for a baseline."""
        from ..methods import CERPE_METHODS

        return self.sets if method in CERPE_METHODS else None


def context(profile: str = "fixture", models: str = "offline", build: bool = True,
            methods: Sequence[str] = RUN_METHODS, root: Path | None = None, progress: bool = True,
            validate: bool = False) -> PaperContext:
    """Locate (and with ``build``, create or resume) every run of a notebook profile.

    ``fixture``: the synthetic fixture suite, runs cached in ``build/fixture/runs``
    (built when missing, reused when current). ``paper-default``: the paper suite
    in ``build/runs`` (what ``cerpe paper`` builds). The stale runs of a setting are built as ``cerpe paper``'s
    jobs are (:func:`cerpe.pipeline.schedule.methods_job`), in this process. ``validate`` loads every
    enabled setting even when its runs are cached (surfaces data errors).
    """
    root = Path(root or ROOT)
    if models not in MODELS:
        raise PaperError(f"unknown models {models!r}; known: {', '.join(MODELS)}")
    lay = layout(profile, models, root)
    suite = "fixture" if profile == "fixture" else "paper-default"
    ctx = PaperContext(profile, suite, models, lay["runs"], lay["figures"], lay["tables"], lay["notebooks"])
    ctx.settings = discover_settings(profile, suite, root / "datasets_manifest", lay["manifests"], load=validate)
    for e in ctx.settings:
        if e.status != "ok":
            continue
        for m in methods:
            ctx.run_dirs[(e.name, m)] = ctx.runs_root / e.name / m
        stale = [m for m in methods if build and not run_is_current(ctx.run_dirs[(e.name, m)], e.run_manifest, m,
                                                                     sets=ctx.sets_of(m))]
        if stale and ensure_loaded(e):
            for group in method_groups(stale):
                err = methods_job(e.run_manifest, group, ctx.runs_root, ctx.sets, setting=e.setting, progress=progress)
                if err:
                    msg = f"{e.name}/{'+'.join(group)}: {err}"
                    log.error(msg)
                    ctx.errors.append(msg)
                    for m in group:
                        ctx.run_dirs.pop((e.name, m))
        if e.status != "ok":
            log.error("setting %s: %s", e.name, e.detail)
            ctx.errors.append(f"{e.name}: {e.detail}")
            for m in methods:
                ctx.run_dirs.pop((e.name, m), None)
    return ctx


def frames(ctx: PaperContext, setting: str | None = None) -> pd.DataFrame:
    """Evaluated frames (``evaluate.frame_errors``) of every run of ``ctx`` (or one setting)."""
    dirs = [p for (s, m), p in ctx.run_dirs.items() if setting is None or s == setting]
    if not dirs:
        raise EvalError(f"no finished runs for {setting or 'any setting'} under {ctx.runs_root}")
    f, _ = evaluate_runs(dirs)
    return f

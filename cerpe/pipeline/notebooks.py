"""The notebooks of ``cerpe paper``: executed with papermill into ``build/notebooks/``, where they write
``tables/`` and ``figures/``; not executed again while their inputs' fingerprint (run
fingerprints, notebooks, evaluation and plotting code, parameters) is unchanged and every
output exists.
"""
from __future__ import annotations

import hashlib
import json
import logging
import time
from pathlib import Path

from ..atomicio import atomic_write_json
from .paper_context import PaperContext
from .paper_settings import ROOT, PaperError
from .table1 import EXPECTED_TABLES

log = logging.getLogger(__name__)

NOTEBOOKS: tuple[str, ...] = ("01_main_results", "02_error_analysis", "03_qualitative", "04_communication_runtime",
                              "05_uncertainty", "06_message_loss", "07_pareto")
# outputs each notebook must leave (stems; figures as .png and .pdf)
EXPECTED_FIGURES: tuple[str, ...] = ("error_analysis", "communication_runtime", "gate_quality", "calibration",
                                     "message_loss", "pareto")
NOTEBOOK_TABLES: tuple[str, ...] = ("communication_runtime.csv", "gate_quality.csv",  # written by notebook 04
                                    "calibration.csv",  # notebook 05
                                    "message_loss.csv", "message_loss.md",  # notebook 06
                                    "pareto.csv", "pareto.md")  # notebook 07
# a `cerpe bench --out` measurement the runtime figure prefers to the runs' own timings
BENCH_JSON = Path("build") / "bench.json"


def notebook_code(root: Path = ROOT) -> list[Path]:
    """The cerpe modules the notebooks import, transitively (:func:`cerpe.importgraph.closure`): the code
    whose output they show, so that editing it runs them again."""
    import ast

    from .. import importgraph

    entries: set[str] = set()
    known = importgraph.modules()
    for n in NOTEBOOKS:
        nb = json.loads((root / "notebooks" / f"{n}.ipynb").read_text())
        for cell in nb.get("cells", []):
            if cell.get("cell_type") != "code":
                continue
            src = "".join(cell.get("source", ""))
            lines = [ln for ln in src.splitlines() if not ln.lstrip().startswith(("%", "!"))]
            try:
                tree = ast.parse("\n".join(lines))
            except SyntaxError:
                continue
            for node in ast.walk(tree):
                if isinstance(node, ast.Import):
                    entries.update(a.name for a in node.names)
                elif isinstance(node, ast.ImportFrom) and node.module:
                    entries.add(node.module)
                    entries.update(f"{node.module}.{a.name}" for a in node.names)
    mods = importgraph.closure(sorted(e for e in entries if e in known))
    return [known[m] for m in mods]


def inputs_fingerprint(ctx: PaperContext, params: dict) -> str:
    h = hashlib.sha256(json.dumps(params, sort_keys=True).encode())
    for key, p in [*sorted(ctx.run_dirs.items()), *((str(q), q) for q in sorted(ctx.extra_runs))]:
        h.update(str(key).encode())
        for f in sorted(p.glob("*/DONE.json")) + [p / "run.json"]:
            if f.exists():
                h.update(f.read_bytes())
    for e in ctx.settings:
        h.update(f"{e.name}:{e.status}:{e.detail}".encode())
    code = notebook_code() + [ROOT / "notebooks" / f"{n}.ipynb" for n in NOTEBOOKS] + [ROOT / BENCH_JSON]
    for f in code:
        if f.exists():
            h.update(f.read_bytes())
    return h.hexdigest()[:20]


def expected_outputs(ctx: PaperContext) -> list[Path]:
    out = [ctx.tables_dir / t for t in EXPECTED_TABLES + NOTEBOOK_TABLES]
    for stem in EXPECTED_FIGURES:
        out += [ctx.figures_dir / f"{stem}.png", ctx.figures_dir / f"{stem}.pdf"]
    for e in ctx.ok_settings:
        out += [ctx.figures_dir / f"qualitative_{e.name}.png"]
    return out


def run_notebooks(ctx: PaperContext, force: bool = False) -> bool:
    """Execute the notebooks with papermill unless inputs and outputs are unchanged. Returns True if run."""
    params = {"PROFILE": ctx.profile, "MODELS": ctx.models}
    fp = inputs_fingerprint(ctx, params)
    stamp = ctx.notebooks_dir / "inputs.json"
    if not force and stamp.exists() and all(p.exists() for p in expected_outputs(ctx)):
        try:
            if json.loads(stamp.read_text()).get("fingerprint") == fp:
                log.info("notebooks: inputs unchanged and outputs present; not executed again")
                return False
        except json.JSONDecodeError:
            pass
    import papermill as pm

    ctx.notebooks_dir.mkdir(parents=True, exist_ok=True)
    for nb in NOTEBOOKS:
        src = ROOT / "notebooks" / f"{nb}.ipynb"
        dst = ctx.notebooks_dir / f"{nb}.ipynb"
        t0 = time.perf_counter()
        try:
            pm.execute_notebook(str(src), str(dst), parameters=params, cwd=str(ROOT / "notebooks"),
                                progress_bar=False, kernel_name="python3")
        except Exception as exc:  # papermill wraps the cell error; name the notebook and the error
            why = (f"{getattr(exc, 'ename', '')}: {getattr(exc, 'evalue', '')}" if hasattr(exc, "ename")
                   else next((ln for ln in str(exc).splitlines() if ln.strip()), type(exc).__name__))
            raise PaperError(f"notebook {src.name} failed (executed copy: {dst}): {why[:300]}") from None
        log.info("notebook %s: %.1f s", nb, time.perf_counter() - t0)
    atomic_write_json(stamp, {"fingerprint": fp, "params": params})
    return True

"""``synthetic`` adapter: generate a synthetic suite on demand (cached), then read it as ``mocap``.

Manifest::

    name: synthetic-cad
    adapter: synthetic
    world: cad-intersection        # cad-intersection | indoor-team (worlds of cerpe.synth)
    suite: paper-default           # fixture | paper-default (size presets of cerpe.synth)
    seed: 0                        # generator seed (same seed -> same data)
    metric_depth: mono-sim
    cache_dir: null                # optional; default $CERPE_CACHE/synth or <project>/build/synth

The suite is rendered once into ``<cache>/<world>-<suite>-seed<N>/`` (written to a
temporary folder and renamed, so an interrupted generation never looks
finished) by ``cerpe.synth``; that folder holds a ``manifest.yaml`` in the mocap
layout, which is then loaded unchanged by the ``mocap`` adapter. The setting
keeps this manifest's ``name``, ``metric_depth`` and ``evaluation``.
"""
from __future__ import annotations

import importlib
import inspect
import logging
import os
import shutil
import tempfile
from pathlib import Path

from ..scene import Setting
from .manifest import Manifest, ManifestError, Problem, type_name
from .report import LoadReport

log = logging.getLogger("cerpe.datasets.synthetic")

WORLDS: tuple[str, ...] = ("cad-intersection", "indoor-team")
SUITES: tuple[str, ...] = ("fixture", "paper-default")
GENERATED_MANIFEST = "manifest.yaml"


def project_root() -> Path:
    """The source checkout holding this package (where ``build/`` lives), else the working directory."""
    here = Path(__file__).resolve().parents[2]
    return here if (here / "pyproject.toml").is_file() else Path.cwd()


def cache_root(manifest: Manifest | None = None) -> Path:
    """Where generated suites go: manifest ``cache_dir``, else ``$CERPE_CACHE/synth``, else ``build/synth``."""
    if manifest is not None and manifest.raw.get("cache_dir"):
        return manifest.resolve(manifest.raw["cache_dir"])
    env = os.environ.get("CERPE_CACHE")
    if env:
        return Path(env).expanduser().resolve() / "synth"
    return project_root() / "build" / "synth"


def _call_generator(world: str, suite: str, seed: int, out_dir: Path) -> None:
    """Render one world's suite into ``out_dir`` with ``cerpe.synth`` (the only coupling to it)."""
    try:
        synth = importlib.import_module("cerpe.synth")
    except ModuleNotFoundError as exc:
        raise ManifestError(f"the synthetic generator (cerpe.synth) is not available: {exc}", field="adapter") from None
    gen = getattr(synth, "generate_suite", None)
    if gen is None:
        raise ManifestError("cerpe.synth has no generate_suite(world, out_dir, ...)", field="adapter")
    params = inspect.signature(gen).parameters
    kwargs: dict = {}
    if "suite" in params:
        kwargs["suite"] = suite
    if "seed" in params:
        kwargs["seed"] = seed
    if "conf" in params and "suite" not in params:
        preset = getattr(synth, "suite_conf", None)
        kwargs["conf"] = preset(suite, world=world, seed=seed) if callable(preset) else {"suite": suite, "seed": seed}
    gen(world, out_dir, **kwargs)


def ensure_generated(world: str, suite: str, seed: int, root: Path) -> Path:
    """The generated suite folder, rendering it first when absent; returns its manifest path."""
    folder = root / f"{world}-{suite}-seed{seed}"
    manifest = folder / GENERATED_MANIFEST
    if manifest.is_file():
        return manifest
    root.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=f".{folder.name}.", dir=root))
    try:
        log.info("generating synthetic suite %s (world %s, seed %d) into %s", suite, world, seed, folder)
        _call_generator(world, suite, seed, tmp)
        if not (tmp / GENERATED_MANIFEST).is_file():
            raise ManifestError(f"cerpe.synth wrote no {GENERATED_MANIFEST} into {tmp}", field="world")
        if folder.exists():  # a concurrent run finished first; keep theirs
            shutil.rmtree(tmp, ignore_errors=True)
        else:
            os.replace(tmp, folder)
    finally:
        if tmp.exists():
            shutil.rmtree(tmp, ignore_errors=True)
    return manifest


class SyntheticAdapter:
    """Generate (once) and load a synthetic suite."""

    name = "synthetic"
    top_level_fields: tuple[str, ...] = ("world", "suite", "seed", "cache_dir")

    def validate(self, manifest: Manifest) -> list[Problem]:
        f, raw = str(manifest.path), manifest.raw
        probs = []
        if raw.get("world") not in WORLDS:
            probs.append(Problem(f, "world", f"expected one of {', '.join(WORLDS)}, got {raw.get('world')!r}"))
        if raw.get("suite", "paper-default") not in SUITES:
            probs.append(Problem(f, "suite", f"expected one of {', '.join(SUITES)}, got {raw.get('suite')!r}"))
        seed = raw.get("seed", 0)
        if isinstance(seed, bool) or not isinstance(seed, int) or seed < 0:
            probs.append(Problem(f, "seed", f"expected a non-negative integer, got {seed!r}"))
        if "cache_dir" in raw and raw["cache_dir"] is not None and not isinstance(raw["cache_dir"], str):
            probs.append(Problem(f, "cache_dir", f"expected a path string, got {type_name(raw['cache_dir'])}"))
        if manifest.encounters is not None:
            probs.append(Problem(f, "encounters", "not used by the synthetic adapter (the generator decides them); remove it"))
        return probs

    def load(self, manifest: Manifest, report: LoadReport) -> Setting:
        from . import load_manifest  # late: the package imports this module lazily through the registry
        from .mocap import MocapAdapter

        raw = manifest.raw
        world, suite, seed = raw["world"], raw.get("suite", "paper-default"), int(raw.get("seed", 0))
        try:
            generated = ensure_generated(world, suite, seed, cache_root(manifest))
        except ManifestError as exc:
            report.extend([Problem(str(manifest.path), p.field or "world", p.message) for p in exc.problems])
            report.raise_if_problems()
            raise
        inner = load_manifest(generated)
        setting = MocapAdapter().load(inner, report)
        setting.name = manifest.name
        setting.metric_depth = manifest.metric_depth
        setting.meta.update({"manifest": str(manifest.path), "adapter": self.name, "generated_manifest": str(generated),
                             "world": world, "suite": suite, "seed": seed})
        return setting

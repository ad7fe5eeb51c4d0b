"""``synthetic`` adapter: generate a synthetic suite on demand (cached), then read it as ``mocap``.

Manifest::

    name: synthetic-cad
    adapter: synthetic
    world: cad-intersection        # cad-intersection | indoor-team (worlds of cerpe.synth)
    suite: paper-default           # fixture | paper-default (size presets of cerpe.synth)
    seed: 0                        # generator seed (same seed -> same data)
    metric_depth: mono-sim
    cache_dir: null                # optional; default $CERPE_CACHE/synth or <project>/build/synth

The world's generator arguments come from the suite preset of ``cerpe.synth``
(``SUITES[suite]``) with ``seed`` replaced. The suite is rendered once into
``<cache>/<suite>/<world>-seed<N>/`` by ``cerpe.synth.generate_suite`` (cached on
its arguments; written to a ``.partial`` folder and renamed, so an interrupted
generation never looks finished). That folder holds a ``manifest.yaml`` in the
mocap layout, which is then loaded unchanged by the ``mocap`` adapter. The
setting keeps this manifest's ``name``, ``metric_depth`` and ``evaluation``.
"""
from __future__ import annotations

import logging
from pathlib import Path
from typing import Callable

from ..errors import CerpeError
from ..scene import Setting
from .manifest import Manifest, ManifestError, Problem, cache_base, checked_manifest, read_yaml, type_name
from .report import LoadReport

log = logging.getLogger("cerpe.datasets.synthetic")

WORLDS: tuple[str, ...] = ("cad-intersection", "indoor-team")
SUITES: tuple[str, ...] = ("fixture", "paper-default")


def cache_root(manifest: Manifest | None = None) -> Path:
    """Where generated suites go: manifest ``cache_dir``, else ``$CERPE_CACHE/synth``, else ``build/synth``."""
    if manifest is not None and manifest.raw.get("cache_dir"):
        return manifest.resolve(manifest.raw["cache_dir"])
    return cache_base() / "synth"


def _synth_api() -> tuple[Callable[..., Path], dict]:
    """``(generate_suite, SUITES)`` from ``cerpe.synth`` (the only coupling to the generator)."""
    from ..synth import SUITES, generate_suite  # heavy (renderer): only when a synthetic setting is loaded

    return generate_suite, SUITES


def suite_conf(suites: dict, suite: str, world: str, seed: int) -> dict:
    """The generator arguments of ``world`` in the named suite preset, with ``seed`` replaced."""
    for _setting, (w, conf) in suites.get(suite, {}).items():
        if w == world:
            return {**conf, "seed": seed}
    raise ManifestError(f"cerpe.synth has no world {world!r} in suite {suite!r}", field="world")


def ensure_generated(world: str, suite: str, seed: int, root: Path, progress: bool = True) -> Path:
    """Render the suite into ``root/<suite>/<world>-seed<N>/`` unless already there; its manifest path.

    ``cerpe.synth.generate_suite`` keys its cache on the generator arguments and
    renders into a ``.partial`` folder renamed at the end, so an interrupted run
    never looks finished; ``force`` lets a changed preset replace a stale folder.
    """
    generate_suite, suites = _synth_api()
    conf = suite_conf(suites, suite, world, seed)
    folder = root / suite / f"{world}-seed{seed}"
    try:
        path = Path(generate_suite(world, folder, conf, force=True, progress=progress))
    except CerpeError as exc:
        raise ManifestError(f"cerpe.synth failed for world {world!r}, suite {suite!r}, seed {seed}: {exc}",
                            field="world") from None
    if not path.is_file():
        raise ManifestError(f"cerpe.synth wrote no manifest ({path})", field="world")
    return path


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
        from .mocap import MocapAdapter

        raw = manifest.raw
        world, suite, seed = raw["world"], raw.get("suite", "paper-default"), int(raw.get("seed", 0))
        try:
            generated = ensure_generated(world, suite, seed, cache_root(manifest))
        except ManifestError as exc:
            report.extend([Problem(str(manifest.path), p.field or "world", p.message) for p in exc.problems])
            report.raise_if_problems()
            raise
        mocap, path = MocapAdapter(), generated.resolve()  # the generated manifest is always mocap's
        inner = checked_manifest(read_yaml(path), path, mocap)
        setting = mocap.load(inner, report)
        setting.name = manifest.name
        setting.metric_depth = manifest.metric_depth  # this manifest's source and options, not the generated one's
        setting.metric_depth_options = dict(manifest.metric_depth_options)
        setting.meta.update({"manifest": str(manifest.path), "adapter": self.name, "generated_manifest": str(generated),
                             "world": world, "suite": suite, "seed": seed})
        return setting

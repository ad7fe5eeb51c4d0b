"""Dataset adapters: manifests in, :class:`cerpe.scene.Setting` out.

Public API::

    load_manifest(path) -> Manifest                 # validate a YAML manifest (all problems at once)
    load_setting(path_or_manifest) -> Setting       # validate, read the data with its adapter, check it
    find_manifests(folder) -> list[Manifest]        # every manifest in a folder, enabled or not

Adapters:

* ``mocap``: image folders + TUM/EuRoC/CSV trajectories (also what ``cerpe synth`` writes);
* ``openmars``: nuScenes-format multi-agent tables;
* ``synthetic``: generate a suite on demand, then ``mocap``;
* ``tum-rgbd``: TUM RGB-D sequences;
* ``frames``: 7-Scenes / 3DMatch / SUN3D frame folders;
* ``pairs``: SuperGlue / LoFTR pair lists;
* ``example``: a KITTI-odometry-style template;
* more through the ``cerpe.adapters`` entry points.

Ground-truth co-visibility from depth
and poses: :mod:`cerpe.datasets.covisibility`; downloads: ``cerpe data``.
"""
from __future__ import annotations

import os
from pathlib import Path

from ..scene import Setting
from .manifest import Manifest, ManifestError, Problem, checked_manifest, read_yaml
from .registry import Adapter, get_adapter, known_adapters, register_adapter
from .report import LoadReport
from .verify import SAMPLE, check_setting

__all__ = [
    "Adapter", "LoadReport", "Manifest", "ManifestError", "Problem", "disabled_reason", "find_manifests", "get_adapter",
    "known_adapters", "load_manifest", "load_setting", "register_adapter",
]

MANIFEST_SUFFIXES = (".yaml", ".yml")


def load_manifest(path: str | os.PathLike) -> Manifest:
    """Parse and validate a manifest file; raises :class:`ManifestError` listing every problem.

    Adapter-specific checks run for enabled and disabled manifests alike (they
    do not read data); a disabled manifest may leave ``data_root`` unresolved.
    """
    path = Path(path).resolve()
    raw = read_yaml(path)
    problems: list[Problem] = []
    adapter: Adapter | None = None
    if isinstance(raw, dict) and isinstance(raw.get("adapter"), str) and raw["adapter"]:
        try:
            adapter = get_adapter(raw["adapter"], str(path))
        except ManifestError as exc:
            problems.extend(exc.problems)
    return checked_manifest(raw, path, adapter, problems)


def load_setting(source: str | os.PathLike | Manifest, report: LoadReport | None = None, *,
                 frames: int | str | None = SAMPLE, progress: bool = False, log: bool = True) -> Setting:
    """Validate (when given a path), load a setting with its adapter, then check what was loaded.

    Every adapter's setting goes through the same checks (:func:`cerpe.datasets.verify.check_setting`),
    so what ``cerpe check`` refuses a run refuses too.

    Args:
        source: a manifest path or an already loaded :class:`Manifest`.
        report: collects counted degradations (frames without ground truth,
            unsynchronised frames...), warnings and sync residuals; a fresh one by default.
            Its summary is also stored in ``setting.meta["load_report"]``.
        frames: frames decoded per robot and encounter by the checks: ``"sample"`` (a few,
            evenly spaced: what a run checks), an integer, None (every frame: ``cerpe
            check``), 0 (none; ids, intrinsics and depth file headers are checked all the same).
        progress: a progress bar while frames are decoded.
        log: log the report's warnings and counts (``cerpe check`` prints them itself).

    Raises:
        ManifestError: listing every problem found in the manifest and its data,
            or because the manifest is disabled.
    """
    manifest = source if isinstance(source, Manifest) else load_manifest(source)
    if not manifest.enabled:
        raise ManifestError(disabled_reason(manifest), file=str(manifest.path), field="enabled")
    report = report if report is not None else LoadReport()
    setting = get_adapter(manifest.adapter, str(manifest.path)).load(manifest, report)
    report.raise_if_problems()
    setting.metric_depth = manifest.metric_depth
    setting.metric_depth_options = dict(manifest.metric_depth_options)
    setting.meta.setdefault("manifest", str(manifest.path))
    setting.meta.setdefault("adapter", manifest.adapter)
    check_setting(setting, report, frames, progress)
    report.raise_if_problems()
    if log:
        report.log(setting.name)
    setting.meta["evaluation_every"] = manifest.evaluation_every
    setting.meta["sync_tolerance_s"] = manifest.sync_tolerance_s
    setting.meta["load_report"] = report.as_dict()
    return setting


def disabled_reason(manifest: Manifest) -> str:
    """Why a manifest is not loaded, in words (``enabled: false``, or ``if-present`` without its data)."""
    if manifest.enabled_if_present:
        root = manifest.data_root if manifest.data_root is not None else manifest.raw.get("data_root")
        return f"disabled (not supplied): data_root {root} is not present (enabled: if-present)"
    return "disabled (not supplied): enabled: false; fill data_root and set enabled: true"


def find_manifests(folder: str | os.PathLike) -> list[Manifest]:
    """Every ``*.yaml``/``*.yml`` manifest in ``folder`` (sorted by file name), enabled or not.

    Raises one :class:`ManifestError` listing the problems of all invalid files.
    """
    folder = Path(folder)
    if not folder.is_dir():
        raise ManifestError("manifest folder not found", file=str(folder))
    out: list[Manifest] = []
    problems: list[Problem] = []
    for p in sorted(folder.iterdir()):
        if p.suffix.lower() not in MANIFEST_SUFFIXES or not p.is_file():
            continue
        try:
            out.append(load_manifest(p))
        except ManifestError as exc:
            problems.extend(exc.problems)
    if problems:
        raise ManifestError(problems)
    names = [m.name for m in out]
    dupes = sorted({n for n in names if names.count(n) > 1})
    if dupes:
        raise ManifestError(f"setting name(s) used by more than one manifest: {', '.join(dupes)}",
                            file=str(folder), field="name")
    return out

"""Run one method on every encounter of a dataset manifest and write a run folder.

Usage: ``cerpe run MANIFEST --method M --out RUNDIR [--preset P] [--set KEY=VALUE ...]
[--loss P [--garble P] [--loss-seed N]] [--overwrite] [--wait]``

Methods: ``cerpe`` (Algorithm 1), ``cerpe-wo-em`` (no ego-motion propagation:
only direct estimates), ``cerpe-graph`` (our extension: the same messages, a robust
pose graph per pair instead of the switch, with covariances), ``sift-ransac`` and ``aliked-lightglue`` (per pair and
frame, no scale; ``aliked-lightglue`` stands in for the paper's SuperGlue row),
and ``nope`` / ``co-visnet``, which exit with "not available offline".
The cerpe methods' configuration is the tree of :mod:`cerpe.method_config`: a named ``--preset``
(default ``paper``), the method's own override, then ``--set`` dotted keys (``--set
backbone.models=paper``, ``--set anchors.rot_tol_rad=0.2``), all recorded in ``run.json``.
``--loss`` / ``--garble`` run the cerpe methods' robots over the in-process lossy
channel (:class:`cerpe.transport.LossSpec`, recorded in ``run.json``).

The run folder (its layout: :mod:`cerpe.runfolder`, see ``docs/formats.md``) holds
``run.json`` and per encounter ``steps.csv``, ``robots.csv``, ``poses/``, ``odometry/`` and
``DONE.json`` (written last). Every file is written to a temporary name and renamed. A rerun
skips finished encounters and recomputes unfinished ones (an interrupted run continues). A
folder whose ``run.json`` fingerprint differs (other method, configuration, seed, manifest or
code) is refused unless ``--overwrite`` is given, and so is one written by an older version of
cerpe (another run format). One process writes a folder at a time: another ``cerpe run`` on the
same ``--out`` stops at once naming the process that holds it (exit 2), or waits with ``--wait``.

:func:`run_methods` runs several methods of one setting together: the CERPE methods whose rows
are views of one pass (:mod:`cerpe.pipeline.views`) share each encounter's pass.
"""
from __future__ import annotations

import argparse
import logging
import sys
from pathlib import Path
from typing import Any, Iterator, Mapping, Sequence

from ..errors import CerpeError
from ..methods import BASELINE_METHODS, CERPE_METHODS, METHOD_LABELS, METHODS, UNAVAILABLE, check_method
from ..records import StepResult
from ..runfolder import write
from ..runfolder.layout import RUN_FORMAT, RunError  # noqa: F401  (RUN_FORMAT: the format run folders are written in)
from ..runfolder.lock import RunLock
from ..runfolder.provenance import code_hash, config_dict, file_digest
from ..transport import LossSpec
from .setting import evaluation_every, load_manifest_setting

log = logging.getLogger(__name__)


# --------------------------------------------------------------------------- method construction
def prepare_method(method: str, seed: int, metric_depth: str | None = None,
                   every: int = 1, depth_options: dict | None = None,
                   channel: LossSpec | None = None, preset: str = "paper",
                   sets: Mapping[str, Any] | None = None) -> tuple[dict, write.StepSource]:
    """Build a method once: its parameters (for run.json and the fingerprint) and its step source.

    ``metric_depth`` is the setting's depth source (manifest ``metric_depth``) for
    the cerpe methods; None keeps the models' default; ``depth_options`` its
    keyword options (manifest ``metric_depth_options``); ``channel`` the lossy
    channel of the cerpe methods (None: lossless). ``every`` is the
    setting's evaluation stride: per-frame baselines only compute evaluated steps
    (CERPE runs every step: its odometry and propagation need them). ``preset`` and ``sets``
    (dotted keys): the cerpe methods' configuration tree (:func:`cerpe.method_config.build`).
    The step sources: :mod:`cerpe.pipeline.cerpe_method`, :mod:`cerpe.pipeline.baseline_method`.

    Raises :class:`~cerpe.methods.MethodUnavailable` for ``nope`` / ``co-visnet``.
    """
    _check_request(method, seed, channel, preset, sets)
    if method in BASELINE_METHODS:
        from .baseline_method import baseline_steps

        return baseline_steps(method, seed, every)
    from .cerpe_method import cerpe_steps

    return cerpe_steps(method, seed, metric_depth, depth_options, channel or LossSpec(), preset, sets)


def _check_request(method: str, seed: int, loss: LossSpec | None, preset: str,
                   sets: Mapping[str, Any] | None) -> None:
    """One error for a bad method, seed, loss, preset or ``--set``, before any data is loaded."""
    check_method(method)
    if int(seed) < 0:
        raise RunError(f"--seed {seed}: must be >= 0")
    if method in BASELINE_METHODS and loss is not None and not loss.lossless:
        raise RunError(f"--loss/--garble: {method} exchanges no messages (a per-frame baseline); "
                       f"only the cerpe methods run over the lossy channel")
    if method in CERPE_METHODS:
        from .. import method_config

        try:
            method_config.build(preset, method, sets)
        except method_config.ConfigError as exc:
            raise RunError(str(exc)) from None
    elif sets or preset != "paper":
        raise RunError(f"method {method!r}: --preset and --set configure the cerpe methods only")


# --------------------------------------------------------------------------- the run
def run_method(manifest: Path | str, method: str, out: Path | str, *, preset: str = "paper",
               sets: Mapping[str, Any] | None = None, seed: int = 0, overwrite: bool = False, progress: bool = True,
               setting: Any = None, loss: LossSpec | None = None, wait: bool = False) -> Path:
    """Run ``method`` on every encounter of ``manifest`` into run folder ``out``; returns ``out``.

    ``preset``, ``sets``: a cerpe method's configuration tree (dotted keys; recorded in ``run.json``;
    see :func:`prepare_method`). ``loss``: the cerpe methods' robots talk over a lossy channel (None:
    lossless). ``setting``: the loaded setting of ``manifest`` (loaded when None).

    Finished encounters (``DONE.json`` with this fingerprint) are skipped; a
    folder from another configuration or an older run format raises :class:`RunError` unless
    ``overwrite`` (then it is replaced); a folder another process is writing raises
    :class:`~cerpe.runfolder.lock.RunBusy` unless ``wait``.
    """
    return run_methods(manifest, {method: out}, preset=preset, sets=sets, seed=seed, overwrite=overwrite,
                       progress=progress, setting=setting, loss=loss, wait=wait)[method]


def run_methods(manifest: Path | str, outs: Mapping[str, Path | str], *, preset: str = "paper",
                sets: Mapping[str, Any] | None = None, seed: int = 0, overwrite: bool = False,
                progress: bool = True, setting: Any = None, loss: LossSpec | None = None,
                wait: bool = False) -> dict[str, Path]:
    """Run every method of ``outs`` (``{method: run folder}``) on every encounter of ``manifest``.

    What :func:`run_method` does for one method, for several at once: the CERPE methods whose records
    are views of one pass (same configuration apart from the back end and propagation:
    :attr:`~cerpe.pipeline.cerpe_method.CerpeSteps.pass_key`) run that pass once per encounter, and
    each one's folder is written from its view, the same records its own run gives. ``preset`` and
    ``sets`` configure the cerpe methods only: with them, ``outs`` holds cerpe methods only. Returns
    ``{method: folder}``.
    """
    if len({Path(o).resolve() for o in outs.values()}) != len(outs):
        raise RunError(f"one run folder per method, got {dict(outs)}")
    for m in outs:  # a bad request is one error before any data is loaded
        _check_request(m, seed, loss, preset, sets)
    outs = {m: write.check_out(o) for m, o in outs.items()}
    manifest = Path(manifest).resolve()
    if setting is None and not manifest.is_file():
        raise RunError(f"manifest not found: {manifest}")
    locks = {m: RunLock(outs[m], wait=wait) for m in sorted(outs, key=lambda m: str(outs[m].resolve()))}
    folders: dict[str, write.RunFolder] = {}
    try:
        for lock in locks.values():  # before any data is loaded: a busy folder stops the run at once
            lock.acquire()
        setting = setting if setting is not None else load_manifest_setting(manifest)
        every = evaluation_every(setting, manifest)
        steps = {m: _prepare(m, manifest, setting, every, seed, loss, preset, sets) for m in outs}
        for m, out in outs.items():
            config, record = _run_json(m, manifest, setting, every, seed, loss, steps[m][0], preset, sets)
            folders[m] = write.open_run(out, config, record, overwrite=overwrite, lock=locks[m])
        _write_encounters(setting, {m: s for m, (_, s) in steps.items()}, folders, progress)
    finally:
        for lock in locks.values():
            lock.release()
    return dict(outs)


def _prepare(method: str, manifest: Path, setting: Any, every: int, seed: int, loss: LossSpec | None, preset: str,
             sets: Mapping[str, Any] | None) -> tuple[dict, write.StepSource]:
    from ..backbones.depth import DepthSourceError

    lossy = {} if loss is None or loss.lossless else {"channel": loss}  # test doubles take no channel
    depth = getattr(setting, "metric_depth", None)
    try:
        return prepare_method(method, seed, depth, every, getattr(setting, "metric_depth_options", None),
                              **lossy, **({"preset": preset} if preset != "paper" else {}),
                              **({"sets": dict(sets)} if sets else {}))
    except DepthSourceError as exc:  # the manifest's depth source: name the file and its fields
        raise RunError(f"{manifest}: metric_depth {depth!r} / metric_depth_options: {exc}") from None


def _run_json(method: str, manifest: Path, setting: Any, every: int, seed: int, loss: LossSpec | None, mconf: dict,
              preset: str, sets: Mapping[str, Any] | None) -> tuple[dict, dict]:
    """``(config, record)`` of ``run.json`` (:func:`cerpe.runfolder.write.open_run`)."""
    from ..threads import torch_threads

    ours = method in CERPE_METHODS
    config = {
        "method": method, "preset": preset if ours else "n/a",
        "seed": int(seed), "setting": setting.name, "manifest_sha": file_digest(manifest),
        "encounters": [e.name for e in setting.encounters], "evaluation_every": every,
        "method_config": mconf, "code": code_hash(method),
        "torch_threads": torch_threads(),  # a CPU convolution's last bits depend on it (cerpe.threads)
    }
    if sets:
        config["sets"] = config_dict(dict(sets))
    record = {
        "method": method,
        "label": METHOD_LABELS[method] + ("" if loss is None or loss.lossless else
                                          f" (loss {loss.p_drop:.0%}, garble {loss.p_garble:.0%}, seed {loss.seed})"),
        "metric_scale": ours and getattr(setting, "metric_depth", None) != "none",
        "manifest": str(manifest), "seed": int(seed), "preset": config["preset"], "setting": setting.name,
        "channel": mconf.get("channel", "n/a"),
    }
    return config, record


def _write_encounters(setting: Any, steps: Mapping[str, write.StepSource], folders: Mapping[str, write.RunFolder],
                      progress: bool) -> None:
    """Every unfinished encounter of each folder; one pass for the methods that share it."""
    from tqdm import tqdm

    todo = {m: {e.name for e in f.todo(setting.encounters)} for m, f in folders.items()}
    groups: dict[Any, list[str]] = {}
    for m, s in steps.items():  # methods sharing a pass; any other method on its own
        key = getattr(s, "pass_key", None)
        groups.setdefault(m if key is None else ("pass", key), []).append(m)
    encs = [e for e in setting.encounters if any(e.name in t for t in todo.values())]
    names = "+".join(folders)
    if not encs:
        log.info("%s/%s: all %d encounters already finished", setting.name, names, len(setting.encounters))
    for enc in tqdm(encs, desc=f"{setting.name}/{names}", unit="enc", disable=not progress, dynamic_ncols=True):
        for group in groups.values():
            need = [m for m in group if enc.name in todo[m]]
            if len(need) == 1 and len(group) == 1:
                folders[need[0]].write_encounter(enc, steps[need[0]], progress)
            elif need:
                _write_views(enc, [(steps[m], folders[m]) for m in need], progress)


def _write_views(enc: Any, members: Sequence[tuple[Any, write.RunFolder]], progress: bool) -> None:
    """One pass of ``enc``, written through the first member's view as it runs, then the others' views."""
    first, folder = members[0]
    records: list[StepResult] = []  # records only (no images): a few MB per encounter

    def viewed(encounter: Any) -> Iterator[StepResult]:
        for res in first.full_pass(encounter):
            records.append(res)
            yield first.view(res)

    folder.write_encounter(enc, viewed, progress)
    for source, other in members[1:]:
        other.write_encounter(enc, lambda _enc, v=source.view: (v(r) for r in records), progress)


# --------------------------------------------------------------------------- CLI
def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("manifest", type=Path, help="dataset manifest (datasets_manifest/*.yaml)")
    p.add_argument("--method", required=True, choices=METHODS,
                   help="cerpe | cerpe-wo-em (no propagation) | cerpe-graph (ours: pose graph) | sift-ransac | "
                        "aliked-lightglue "
                        "(SuperGlue stand-in) | nope, co-visnet (not available offline)")
    p.add_argument("--out", required=True, type=Path, help="run folder to write (resumed when it exists)")
    p.add_argument("--preset", default="paper", metavar="P",
                   help="cerpe methods: a named configuration (default: paper, the paper's protocol); "
                        "`cerpe config show --presets` lists them")
    p.add_argument("--seed", type=int, default=0, help="random seed (RANSAC; the lossy channel's unless --loss-seed)")
    p.add_argument("--loss", type=float, default=0.0, metavar="P",
                   help="cerpe methods: run the robots over the in-process lossy channel, each frame (descriptor, "
                        "pose, image request, image reply) dropped on its way to each receiver with probability P "
                        "(default 0: lossless). Losses are counted per robot and step (msg:lost, and what the "
                        "robot did about it: descriptor:missing, msg:reply-missing, pose:stale, pose:bridged); "
                        "recorded in run.json, part of the run's fingerprint")
    p.add_argument("--garble", type=float, default=0.0, metavar="P",
                   help="with --loss: probability that a frame that arrives is corrupted (bytes flipped or cut; "
                        "counted msg:garbled, never used; default 0)")
    p.add_argument("--loss-seed", type=int, default=None, metavar="N",
                   help="seed of the channel's draws (default: --seed); the same seed reproduces the run bit for "
                        "bit, another seed draws other losses")
    p.add_argument("--set", action="append", default=[], metavar="KEY=VALUE", dest="sets",
                   help="cerpe methods: one knob of the configuration tree by its dotted path, the value as YAML "
                        "(true, 0.3, paper), e.g. --set policy.mode=pays, --set backbone.models=paper; repeatable. "
                        "`cerpe config show` lists every knob; an unknown key is an error listing the known ones. "
                        "Recorded in run.json, part of the run's fingerprint")
    p.add_argument("--overwrite", action="store_true",
                   help="replace a run folder written with another configuration instead of refusing")
    p.add_argument("--wait", action="store_true",
                   help="when another process is writing --out, wait for it to finish instead of stopping")
    p.add_argument("--no-progress", action="store_true", help="no progress bars")


def parse_sets(items: Sequence[str]) -> dict[str, Any]:
    """``--set KEY=VALUE`` arguments -> dotted overrides (:func:`cerpe.method_config.parse_sets`)."""
    from ..method_config import ConfigError
    from ..method_config import parse_sets as parse

    try:
        return parse(items)
    except ConfigError as exc:
        raise RunError(str(exc)) from None


def main(args: argparse.Namespace) -> int:
    if args.method in UNAVAILABLE:
        print(f"cerpe run: error: method {args.method!r} not available offline: {UNAVAILABLE[args.method]}",
              file=sys.stderr)
        return 2
    if args.loss == 0 and args.garble == 0 and args.loss_seed is not None:
        raise RunError("--loss-seed: only with --loss P (or --garble P); without them the channel loses nothing")
    loss = None if args.loss == 0 and args.garble == 0 else \
        LossSpec(args.loss, args.garble, args.seed if args.loss_seed is None else args.loss_seed)
    out = run_method(args.manifest, args.method, args.out, preset=args.preset, sets=parse_sets(args.sets) or None,
                     seed=args.seed, overwrite=args.overwrite, progress=not args.no_progress, loss=loss,
                     wait=args.wait)
    print(f"run folder: {out}")
    from .eval_cli import run_summary

    try:
        print(run_summary(out))
    except CerpeError as exc:  # e.g. no frame with ground truth: the run itself is fine
        print(f"(no summary: {exc})")
    return 0

"""Run one method on every encounter of a dataset manifest and write a run folder.

Usage: ``cerpe run MANIFEST --method M --out RUNDIR [--preset P] [--set KEY=VALUE ...]
[--loss P [--garble P] [--loss-seed N]]``

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

The run folder (see ``docs/ARCHITECTURE.md``)::

    RUNDIR/run.json                         method, config, fingerprint, versions, seed, git rev
    RUNDIR/<encounter>/steps.csv            one row per ordered pair and step
    RUNDIR/<encounter>/robots.csv           one row per robot and step
    RUNDIR/<encounter>/poses/<i>__<j>.tum   estimate of T_cj_ci (TUM: stamp tx ty tz qx qy qz qw)
    RUNDIR/<encounter>/poses/<i>__<j>.gt.tum
    RUNDIR/<encounter>/poses/<i>__<j>.cov   its 6x6 covariance per stamp (cerpe-graph only; ROS order)
    RUNDIR/<encounter>/odometry/<robot>.tum X_i^t (cerpe methods only)
    RUNDIR/<encounter>/DONE.json            written last; presence = encounter finished

Every file is written to a temporary name and renamed. A rerun skips finished
encounters and recomputes unfinished ones (an interrupted run continues). A
folder whose ``run.json`` fingerprint differs (other method, configuration,
seed, manifest or code) is refused unless ``--overwrite`` is given, and so is one written by
an older version of cerpe (another run format).
"""
from __future__ import annotations

import argparse
import dataclasses
import json
import logging
import shutil
import sys
import time
from pathlib import Path
from typing import Any, Callable, Iterator, Mapping, Sequence

import numpy as np

from .. import knobs
from ..atomicio import AtomicIOError, atomic_write_json, atomic_write_text, ensure_dir, read_json
from ..tum import format_tum, format_tum_cov
from ..errors import CerpeError
from ..geometry import se3_inverse, se3_to_tq_xyzw
from ..records import STAGES, PairRecord, RobotRecord, StepResult
from ..transport import LossSpec
from .methods import BASELINE_METHODS, CERPE_METHODS, METHOD_LABELS, METHODS, UNAVAILABLE, check_method
from .provenance import code_hash, config_dict, file_digest, fingerprint, git_revision, package_versions

log = logging.getLogger(__name__)

RUN_FORMAT = 2


class RunError(CerpeError, ValueError):
    """Bad run request or a run folder that cannot be used (other configuration, corrupt file)."""


# --------------------------------------------------------------------------- method construction
StepSource = Callable[[Any], Iterator[StepResult]]


def prepare_method(method: str, seed: int, metric_depth: str | None = None,
                   every: int = 1, depth_options: dict | None = None,
                   channel: LossSpec | None = None, preset: str = "paper",
                   sets: Mapping[str, Any] | None = None) -> tuple[dict, StepSource]:
    """Build a method once: its parameters (for run.json and the fingerprint) and its stepper.

    ``metric_depth`` is the setting's depth source (manifest ``metric_depth``) for
    the cerpe methods; None keeps the models' default; ``depth_options`` its
    keyword options (manifest ``metric_depth_options``); ``channel`` the lossy
    channel of the cerpe methods (None: lossless). ``every`` is the
    setting's evaluation stride: per-frame baselines only compute evaluated steps
    (CERPE runs every step: its odometry and propagation need them). ``preset`` and ``sets``
    (dotted keys): the cerpe methods' configuration tree (:func:`cerpe.method_config.build`).

    Raises :class:`~cerpe.pipeline.methods.MethodUnavailable` for ``nope`` / ``co-visnet``.
    """
    check_method(method)
    if (sets or preset != "paper") and method not in CERPE_METHODS:
        raise RunError(f"method {method!r}: --preset and --set configure the cerpe methods only")
    if method in BASELINE_METHODS:
        if channel is not None and not channel.lossless:
            raise RunError(f"--loss/--garble: {method} exchanges no messages (a per-frame baseline); "
                           f"only the cerpe methods run over the lossy channel")
        steps, conf = _baseline_steps(method, seed, every)
        return {"baseline": conf, "image_exchange": "always (JPEG quality 90)"}, steps
    return _cerpe_steps(method, seed, metric_depth, depth_options, channel or LossSpec(), preset, sets)


def cerpe_plugins_and_config(method: str, metric_depth: str | None, depth_options: dict | None = None,
                             preset: str = "paper", sets: Mapping[str, Any] | None = None) -> tuple[Any, Any, dict]:
    """Plug-ins, resolved :class:`~cerpe.method_config.CerpeConfig` and the run.json parameters of a CERPE method.

    One place for ``cerpe run`` and ``cerpe online``, so both build the same thing.
    """
    from .. import method_config
    from ..backbones.build import build_plugins

    try:
        tree = method_config.build(preset, method, sets)
    except method_config.ConfigError as exc:
        raise RunError(str(exc)) from None
    plugins = build_plugins(tree.backbone, depth=metric_depth, depth_options=depth_options)
    cfg = tree.resolved(getattr(plugins.descriptor, "thresholds", None))
    conf = {
        "tree": config_dict(knobs.as_dict(cfg)), "preset": preset, "sets": config_dict(dict(sets or {})),
        "depth": getattr(plugins.depth, "name", type(plugins.depth).__name__),
        "depth_options": config_dict(dict(depth_options or {})),
    }
    return plugins, cfg, conf


def _cerpe_steps(method: str, seed: int, metric_depth: str | None, depth_options: dict | None = None,
                 loss: LossSpec = LossSpec(), preset: str = "paper",
                 sets: Mapping[str, Any] | None = None) -> tuple[dict, StepSource]:
    """Algorithm 1 with the configuration tree of ``preset``, ``method`` and ``sets``."""
    from .. import algorithm

    plugins, cfg, conf = cerpe_plugins_and_config(method, metric_depth, depth_options, preset, sets)
    conf["channel"] = loss.as_dict()

    # Propagation and the pose graph feed nothing back (anchors come only from direct
    # estimates; the gate, memory, scale and odometry never read a propagated pose or
    # the graph), so the three CERPE rows are views of ONE pass run with propagation and
    # the graph: "cerpe" its switch records (PairRecord.switch), "w/o EM" those with the
    # propagated estimates removed, "cerpe-graph" the pass itself. A CERPE method run
    # after another in the same process reuses the pass (tests/test_pipeline_woem.py
    # checks each view against a real run of that configuration).
    backend = cfg.backend
    pass_cfg = dataclasses.replace(cfg, backend=dataclasses.replace(backend, propagate=True, kind="graph"))
    # ... unless something reads the graph back: the "pays" request policy reads its sigma
    shared = ((backend.propagate, backend.kind) in ((True, "switch"), (False, "switch"), (True, "graph"))
              and cfg.policy.mode in ("gate", "always"))
    tree = conf["tree"]
    pass_key = json.dumps({**conf, "sets": None, "tree": {**tree, "backend": {**tree["backend"], "propagate": None,
                                                                              "kind": None}}},
                          sort_keys=True, default=str)

    def view(res: StepResult) -> StepResult:
        if backend.kind == "graph":
            return res
        res = switch_view(res)
        return res if backend.propagate else without_propagation(res)

    def steps(encounter: Any) -> Iterator[StepResult]:
        channel = None if loss.lossless else loss.channel(encounter.robot_ids, encounter.name)
        if not shared:  # a configuration whose records are not a view of the shared pass
            yield from algorithm.run_encounter(encounter, plugins.descriptor, plugins.backbone, plugins.depth,
                                               config=cfg, channel=channel, seed=seed)
            return
        key = (pass_key, seed, _encounter_identity(encounter))
        if key in _FULL_PASSES:
            for res in _FULL_PASSES[key]:
                yield view(res)
            return
        keep: list[StepResult] = []
        for res in algorithm.run_encounter(encounter, plugins.descriptor, plugins.backbone, plugins.depth,
                                           config=pass_cfg, channel=channel, seed=seed):
            keep.append(res)
            yield view(res)
        _FULL_PASSES[key] = keep  # records only (no images): a few MB per setting
        while len(_FULL_PASSES) > _KEEP_PASSES:
            _FULL_PASSES.pop(next(iter(_FULL_PASSES)))

    return conf, steps


_FULL_PASSES: dict[tuple, list[StepResult]] = {}
_KEEP_PASSES = 64  # encounters' passes kept in the process (oldest dropped first)


def switch_view(res: StepResult) -> StepResult:
    """The paper's CERPE (``backend="switch"``) view of a step run with ``backend="graph"``.

    Pair estimates come from :attr:`PairRecord.switch`; the graph's degradations and
    its stage time are removed. A step without switch records is returned as it is.
    """
    if not any(p.switch is not None for p in res.pairs):
        return res
    pairs = []
    for p in res.pairs:
        if p.switch is not None:
            source, T, reason, anchor_step = p.switch
            p = dataclasses.replace(p, source=source, T_cj_ci=T, reason=reason, anchor_step=anchor_step,
                                    cov=None, switch=None)
        pairs.append(p)
    robots = [dataclasses.replace(r, timings_s={**r.timings_s, "graph": 0.0},
                                  degradations=[d for d in r.degradations if not d.startswith("graph:")])
              for r in res.robots]
    return StepResult(step=res.step, pairs=pairs, robots=robots)


def _encounter_identity(encounter: Any) -> str:
    first = [str(r.frame_ids[0]) if len(r) else "" for r in encounter.robots]
    return json.dumps([encounter.name, encounter.n_steps, encounter.robot_ids, first])


def without_propagation(res: StepResult) -> StepResult:
    """The "w/o EM" view of a full CERPE step: propagated estimates become ``none``."""
    pairs = []
    for p in res.pairs:
        # reasons that only a propagated (or no longer propagated) estimate has
        carried = ("stale-pose", "no-anchor", "no-pose-of-other", "unverified", "unverified-expired")
        if p.source == "propagated" or (p.source == "none" and any(r in carried for r in p.reason.split("; "))):
            parts = [r for r in p.reason.split("; ") if r and r not in carried]
            reason = "; ".join(parts) or ("gate-closed" if not p.gate_open else "")
            p = dataclasses.replace(p, source="none", T_cj_ci=None, anchor_step=-1, reason=reason)
        pairs.append(p)
    robots = [dataclasses.replace(r, timings_s={**r.timings_s, "propagation": 0.0},
                                  degradations=[d for d in r.degradations if d != "pose:stale"])
              for r in res.robots]
    return StepResult(step=res.step, pairs=pairs, robots=robots)


def _baseline_steps(method: str, seed: int, every: int = 1) -> tuple[StepSource, dict]:
    """Per-pair, per-frame baseline: each unordered pair once, the reverse direction is its inverse.

    The baseline sees both raw images at every step, i.e. every robot always
    sends its image; the bytes counted are the JPEG image replies it would take.
    """
    from ..baselines import build_baseline
    from ..baselines.base import PairEstimate
    from ..messages import ImageReply

    bl = build_baseline(method, seed=seed)

    def steps(encounter: Any) -> Iterator[StepResult]:
        robots = encounter.robots
        n = len(robots)
        for t in range(encounter.n_steps):
            imgs = [r.image(t) for r in robots]
            reply_bytes = [
                len(ImageReply.from_image(k, t, imgs[k], (r.intrinsics.fx, r.intrinsics.fy,
                                                           r.intrinsics.cx, r.intrinsics.cy)).encode())
                for k, r in enumerate(robots)
            ]
            pairs: dict[tuple[int, int], PairRecord] = {}
            timing = {k: {s: 0.0 for s in STAGES} for k in range(n)}
            evaluated = t % every == 0
            for i in range(n):
                for j in range(i + 1, n):
                    if evaluated:
                        est = bl.estimate(imgs[i], robots[i].intrinsics, imgs[j], robots[j].intrinsics)
                    else:  # independent per frame: a step nobody evaluates need not be computed
                        est = PairEstimate(None, "not-evaluated")
                    dt = float(sum(est.timings_s.values()))
                    timing[i]["backbone"] += dt
                    for (a, b, T) in ((i, j, est.T_cj_ci),
                                      (j, i, None if est.T_cj_ci is None else se3_inverse(est.T_cj_ci))):
                        pairs[(a, b)] = PairRecord(
                            step=t, stamp_s=float(robots[a].stamps_s[t]), ego=robots[a].robot_id,
                            other=robots[b].robot_id, gate_score=float("nan"), gate_open=True,
                            source="direct" if T is not None else "none", T_cj_ci=T,
                            reason=est.reason, bytes_pair=reply_bytes[b], direct_inliers=int(est.n_inliers),
                        )
            recs = [
                RobotRecord(step=t, stamp_s=float(r.stamps_s[t]), robot=r.robot_id,
                            T_odom_cam=np.full((4, 4), np.nan), scale=float("nan"), n_keyframes=0,
                            keyframe=False, bytes_sent={"reply": reply_bytes[k] * (n - 1)},
                            timings_s=timing[k])
                for k, r in enumerate(robots)
            ]
            yield StepResult(step=t, pairs=[pairs[p] for p in encounter.ordered_pairs()], robots=recs)

    return steps, dict(bl.conf)


# --------------------------------------------------------------------------- encounter -> files
def _gt_cols(T: np.ndarray | None) -> dict[str, float]:
    names = ("tx", "ty", "tz", "qx", "qy", "qz", "qw")
    if T is None or not np.all(np.isfinite(T)):
        return {f"gt_{n}": float("nan") for n in names}
    t, q = se3_to_tq_xyzw(T)
    return {f"gt_{n}": float(v) for n, v in zip(names, [*t, *q])}


def _csv_text(rows: list[dict]) -> str:
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
    """Run one encounter and write its files; DONE.json last. Returns DONE's content."""
    from tqdm import tqdm

    idx = {r.robot_id: k for k, r in enumerate(encounter.robots)}
    step_rows: list[dict] = []
    robot_rows: list[dict] = []
    est: dict[tuple[str, str], list[tuple[float, np.ndarray, np.ndarray | None, np.ndarray | None]]] = {}
    odo: dict[str, list[tuple[float, np.ndarray]]] = {r.robot_id: [] for r in encounter.robots}
    t0 = time.perf_counter()
    n_steps = 0
    bar = tqdm(total=encounter.n_steps, desc=f"{encounter.name}", unit="step", disable=not progress,
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
                row = {"encounter": encounter.name, **pr.as_row(), **_gt_cols(T_gt)}
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
    if n_steps != encounter.n_steps:
        raise RunError(f"encounter {encounter.name}: method produced {n_steps} steps for {encounter.n_steps}")
    enc_dir.mkdir(parents=True, exist_ok=True)
    atomic_write_text(enc_dir / "steps.csv", _csv_text(step_rows))
    atomic_write_text(enc_dir / "robots.csv", _csv_text(robot_rows))
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
    atomic_write_json(enc_dir / "DONE.json", done)
    return done


# --------------------------------------------------------------------------- the run
def load_manifest_setting(manifest: Path) -> Any:
    """The :class:`~cerpe.scene.Setting` of ``manifest`` (a RunError if the file is missing)."""
    from .. import datasets

    if not Path(manifest).is_file():
        raise RunError(f"manifest not found: {manifest}")
    return datasets.load_setting(Path(manifest))


def evaluation_every(setting: Any, manifest: Path | None = None) -> int:
    """``evaluation.every`` of a setting (from its meta, else the manifest YAML), default 1."""
    meta = getattr(setting, "meta", {}) or {}
    if "evaluation_every" in meta:
        return int(meta["evaluation_every"])
    ev = meta.get("evaluation")
    if ev is None and manifest is not None:
        import yaml

        try:
            ev = (yaml.safe_load(Path(manifest).read_text()) or {}).get("evaluation")
        except (OSError, yaml.YAMLError):
            ev = None
    every = int((ev or {}).get("every", 1)) if isinstance(ev, dict) else int(ev or 1)
    if every < 1:
        raise RunError(f"{manifest}: evaluation.every must be >= 1, got {every}")
    return every


def run_method(manifest: Path | str, method: str, out: Path | str, *, preset: str = "paper",
               sets: Mapping[str, Any] | None = None, seed: int = 0, overwrite: bool = False, progress: bool = True,
               setting: Any = None, loss: LossSpec | None = None) -> Path:
    """Run ``method`` on every encounter of ``manifest`` into run folder ``out``.

    ``preset``, ``sets``: a cerpe method's configuration tree (dotted keys; recorded in ``run.json``;
    see :func:`prepare_method`). ``loss``: the cerpe methods' robots talk over a lossy channel (None:
    lossless).

    Finished encounters (``DONE.json`` with this fingerprint) are skipped; a
    folder from another configuration or an older run format raises :class:`RunError` unless
    ``overwrite`` (then it is replaced). Returns ``out``.
    """
    check_method(method)
    if int(seed) < 0:
        raise RunError(f"--seed {seed}: must be >= 0")
    if method in BASELINE_METHODS and loss is not None and not loss.lossless:  # before any data is loaded
        raise RunError(f"--loss/--garble: {method} exchanges no messages (a per-frame baseline); "
                       f"only the cerpe methods run over the lossy channel")
    if method in CERPE_METHODS:  # a bad preset or --set: one error before any data is loaded
        from .. import method_config

        try:
            method_config.build(preset, method, sets)
        except method_config.ConfigError as exc:
            raise RunError(str(exc)) from None
    elif sets or preset != "paper":
        raise RunError(f"method {method!r}: --preset and --set configure the cerpe methods only")
    manifest = Path(manifest).resolve()
    out = Path(out)
    ensure_dir(out, "--out", create=False)
    if out.is_dir() and not (out / "run.json").exists() and any(out.iterdir()):
        raise RunError(f"--out {out}: a folder that is not a run folder (no run.json) and not empty; "
                       f"choose another --out (cerpe never writes into a folder it did not make)")
    setting = setting if setting is not None else load_manifest_setting(manifest)
    every = evaluation_every(setting, manifest)
    lossy = {} if loss is None or loss.lossless else {"channel": loss}  # test doubles take no channel
    from ..backbones.depth import DepthSourceError
    from ..threads import torch_threads

    depth = getattr(setting, "metric_depth", None)
    try:
        mconf, steps = prepare_method(method, seed, depth, every, getattr(setting, "metric_depth_options", None),
                                      **lossy, **({"preset": preset} if preset != "paper" else {}),
                                      **({"sets": dict(sets)} if sets else {}))
    except DepthSourceError as exc:  # the manifest's depth source: name the file and its fields
        raise RunError(f"{manifest}: metric_depth {depth!r} / metric_depth_options: {exc}") from None
    config = {
        "format": RUN_FORMAT, "method": method, "preset": preset if method in CERPE_METHODS else "n/a",
        "seed": int(seed), "setting": setting.name, "manifest_sha": file_digest(manifest),
        "encounters": [e.name for e in setting.encounters], "evaluation_every": every,
        "method_config": mconf, "code": code_hash(method),
        "torch_threads": torch_threads(),  # a CPU convolution's last bits depend on it (cerpe.threads)
    }
    if sets:
        config["sets"] = config_dict(dict(sets))
    fp = fingerprint(config)
    run_json = out / "run.json"
    if run_json.exists():
        old = read_json(run_json, "run.json")
        fmt = old.get("config", {}).get("format")
        if fmt != RUN_FORMAT and not overwrite:
            raise RunError(f"{run_json}: written by another version of cerpe (run format {fmt}, this one writes "
                           f"{RUN_FORMAT}); rerun with --overwrite to replace it, or choose another --out")
        if old.get("fingerprint") != fp:
            if not overwrite:
                diff = sorted(k for k in config if old.get("config", {}).get(k) != config[k])
                raise RunError(
                    f"{run_json}: run folder belongs to another configuration (fingerprint "
                    f"{old.get('fingerprint')} != {fp}; differs in {diff}); use another --out or --overwrite")
            log.warning("replacing run folder %s (configuration changed)", out)
            shutil.rmtree(out)
    ensure_dir(out, "--out")
    for stale in out.rglob(".*.tmp"):  # leftovers of an interrupted atomic write
        stale.unlink(missing_ok=True)
    atomic_write_json(run_json, {
        "method": method, "fingerprint": fp, "config": config,
        "label": METHOD_LABELS[method] + ("" if loss is None or loss.lossless else
                                          f" (loss {loss.p_drop:.0%}, garble {loss.p_garble:.0%}, seed {loss.seed})"),
        "metric_scale": method in CERPE_METHODS and getattr(setting, "metric_depth", None) != "none",
        "manifest": str(manifest),
        "package_versions": package_versions(), "git_revision": git_revision(), "seed": int(seed),
        "preset": config["preset"], "setting": setting.name, "command": " ".join(sys.argv),
        "channel": mconf.get("channel", "n/a"),
    })
    from tqdm import tqdm

    todo = []
    for enc in setting.encounters:
        done_path = out / enc.name / "DONE.json"
        if done_path.exists():
            try:
                if read_json(done_path, "DONE.json").get("fingerprint") == fp:
                    continue
            except AtomicIOError as exc:
                log.warning("%s; recomputing encounter %s", exc, enc.name)
        todo.append(enc)
    if not todo:
        log.info("%s/%s: all %d encounters already finished", setting.name, method, len(setting.encounters))
    for enc in tqdm(todo, desc=f"{setting.name}/{method}", unit="enc", disable=not progress, dynamic_ncols=True):
        enc_dir = out / enc.name
        if (enc_dir / "DONE.json").exists():
            (enc_dir / "DONE.json").unlink()
        run_encounter_to_folder(enc, steps, enc_dir, fp, progress=progress)
    return out


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
    loss = None if args.loss == 0 and args.garble == 0 else \
        LossSpec(args.loss, args.garble, args.seed if args.loss_seed is None else args.loss_seed)
    out = run_method(args.manifest, args.method, args.out, preset=args.preset, sets=parse_sets(args.sets) or None,
                     seed=args.seed, overwrite=args.overwrite, progress=not args.no_progress, loss=loss)
    print(f"run folder: {out}")
    return 0

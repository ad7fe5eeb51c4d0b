"""Render planned encounters, in memory or to the mocap-style dataset layout.

On disk (one *setting* folder per world; see docs/formats.md "Dataset manifests")::

    OUT/manifest.yaml                 adapter: mocap, metric_depth: sensor, all encounters
    OUT/meta.json                     generator arguments (the cache key) and encounter names
    OUT/<enc>/overlap.npy             [T,N,N] float32 ground-truth overlap (robot order of the manifest)
    OUT/<enc>/meta.json               scenario, stamps, viewing angles [T,N,N] (radians), precheck flag
    OUT/<enc>/<rid>/rgb/<stamp>.png   8-bit RGB
    OUT/<enc>/<rid>/depth/<stamp>.png uint16 millimetres (depth_units_per_m: 1000); 0 = no surface,
                                      and also 0 beyond 65.535 m (not representable: never clipped)
    OUT/<enc>/<rid>/groundtruth.txt   TUM: stamp tx ty tz qx qy qz qw, camera-to-world (T_body_cam = identity)
    OUT/<enc>/<rid>/camera.yaml       width height fx fy cx cy distortion

Generation is cached: the same arguments (and the same generator source, by
hash) find ``OUT/meta.json`` equal and render nothing; different ones raise
:class:`SynthError` unless ``force``. Work goes into ``.OUT.partial`` and is renamed
to ``OUT`` at the end; finished encounters there are reused after an interruption. A lock file ``.OUT.lock``
makes processes that ask for the same ``OUT`` at once take turns.
"""
from __future__ import annotations

import io
import json
import logging
import os
import shutil
import sys
import time
from contextlib import contextmanager
from pathlib import Path

import numpy as np

from ..atomicio import AtomicIOError, atomic_write_bytes, ensure_dir
from ..depthsim import OUTDOOR_SENSOR
from ..scene import Encounter, RobotStream
from .errors import SynthError
from .groundtruth import has_transition, overlap_matrix, viewing_angle_matrix
from .plan import EncounterPlan
from .renderer import render
from .worlds import WORLDS, check_conf, plan_encounter

log = logging.getLogger(__name__)

SYNTH_VERSION = 1
DEPTH_UNITS_PER_M = 1000

#: defaults of every generator argument (``n_robots`` None = world default: 2 vehicles / 3 robots)
DEFAULT_CONF: dict = {
    "seed": 0,
    "n_encounters": 1,
    "n_robots": None,
    "n_three": 0,          # cad-intersection: this many (last) encounters get 3 vehicles
    "n_frames": 40,
    "fps": 10.0,
    "size": (640, 480),
    "overlap_stride": 4,
    "workers": 1,          # processes rendering encounters in parallel (not part of the cache key)
}

SETTING_OF_WORLD = {"cad-intersection": "synthetic-cad", "indoor-team": "synthetic-indoor"}

# An indoor RGB-D range (0.3-10 m) sees little of a street: most keypoints of the CAD world lie
# farther, and scale alignment then starves for lack of depth pixels.
SENSOR_OPTIONS_BY_WORLD: dict[str, dict[str, float]] = {"cad-intersection": OUTDOOR_SENSOR}


def sensor_options(world: str) -> dict[str, float]:
    """``SensorDepthSim`` keyword options that suit ``world`` (``{}``: the indoor defaults)."""
    return dict(SENSOR_OPTIONS_BY_WORLD.get(world, {}))

#: named suites: setting name -> (world, generator arguments)
SUITES: dict[str, dict[str, tuple[str, dict]]] = {
    "fixture": {
        "synthetic-cad": ("cad-intersection", {"seed": 0, "n_encounters": 1, "n_frames": 12, "fps": 3.0,
                                               "size": (160, 120), "n_robots": 2}),
        "synthetic-indoor": ("indoor-team", {"seed": 0, "n_encounters": 1, "n_frames": 12, "fps": 3.0,
                                             "size": (160, 120), "n_robots": 3}),
    },
    "paper-default": {
        "synthetic-cad": ("cad-intersection", {"seed": 0, "n_encounters": 8, "n_frames": 36, "fps": 10.0,
                                               "size": (640, 480), "n_robots": 2, "n_three": 2, "workers": 2}),
        "synthetic-indoor": ("indoor-team", {"seed": 0, "n_encounters": 4, "n_frames": 36, "fps": 10.0,
                                             "size": (640, 480), "n_robots": 3, "workers": 2}),
    },
}


def full_conf(world: str, conf: dict | None = None) -> dict:
    """Defaults + ``conf``, validated; ``size`` as a ``(W, H)`` tuple of ints."""
    unknown = set(conf or {}) - set(DEFAULT_CONF)
    if unknown:
        raise SynthError(f"unknown generator argument(s) {sorted(unknown)}; known: {sorted(DEFAULT_CONF)}")
    c = {**DEFAULT_CONF, **(conf or {})}
    if c["n_robots"] is None:
        c["n_robots"] = 2 if world == "cad-intersection" else 3
    try:
        c["size"] = (int(c["size"][0]), int(c["size"][1]))
    except (TypeError, ValueError, IndexError):
        raise SynthError(f"size must be (width, height), got {c['size']!r}") from None
    for k in ("seed", "n_encounters", "n_robots", "n_three", "n_frames", "overlap_stride", "workers"):
        c[k] = int(c[k])
    c["fps"] = float(c["fps"])
    check_conf(world, c)
    for k, least in (("n_encounters", 1), ("seed", 0), ("workers", 1), ("n_three", 0), ("overlap_stride", 1)):
        if c[k] < least:
            raise SynthError(f"{k} {c[k]}: must be >= {least}")
    if c["n_three"] > c["n_encounters"]:
        raise SynthError(f"n_three {c['n_three']}: more three-vehicle encounters than encounters ({c['n_encounters']})")
    return c


def encounter_name(world: str, seed: int, index: int) -> str:
    if world == "cad-intersection":
        return f"cad-l{index % 4}-s{seed}-e{index:02d}"
    return f"indoor-s{seed}-e{index:02d}"


def plan_for(world: str, conf: dict, index: int) -> EncounterPlan:
    """The plan of encounter ``index`` of a suite with (full) ``conf``."""
    n = conf["n_robots"]
    if world == "cad-intersection" and index >= conf["n_encounters"] - conf["n_three"]:
        n = max(n, 3)
    plan = plan_encounter(world, conf["seed"], index, {"n_robots": n, "n_frames": conf["n_frames"],
                                                       "fps": conf["fps"], "size": conf["size"]})
    plan.name = encounter_name(world, conf["seed"], index)
    return plan


def iter_frames(plan: EncounterPlan):
    """Yield ``(t, rgbs [N], depths [N])`` for every step (each robot's own body hidden)."""
    for t in range(plan.n_steps):
        outs = [render(plan.faces_at(t, viewer=k), plan.T_world_cam[k, t], plan.intrinsics, plan.ctx)
                for k in range(len(plan.robot_ids))]
        yield t, [o.rgb for o in outs], [o.depth_m for o in outs]


def render_encounter(world: str, seed: int = 0, index: int = 0, conf: dict | None = None,
                     progress: bool = False) -> Encounter:
    """Render one encounter into memory as a :class:`cerpe.scene.Encounter`.

    Images are ``[H,W,3] uint8`` arrays, depth ``[H,W] float32`` metres (exact
    z-depth, 0 = no surface), ``overlap [T,N,N]``; ``meta`` has the plan, the
    viewing angles ``[T,N,N]`` and ``transition`` (overlap crossed 0.3 and 0.05).
    """
    c = full_conf(world, {**(conf or {}), "seed": seed, "n_encounters": max(index + 1, (conf or {}).get("n_encounters", 1))})
    plan = plan_for(world, c, index)
    n, T = len(plan.robot_ids), plan.n_steps
    rgbs = [[None] * T for _ in range(n)]
    depths = [[None] * T for _ in range(n)]
    ov = np.zeros((T, n, n))
    frames = iter_frames(plan)
    if progress:
        from tqdm import tqdm

        frames = tqdm(frames, total=T, desc=plan.name, unit="step")
    for t, rr, dd in frames:
        for k in range(n):
            rgbs[k][t], depths[k][t] = rr[k], dd[k]
        ov[t] = overlap_matrix(dd, [plan.intrinsics] * n, list(plan.T_world_cam[:, t]), c["overlap_stride"])
    robots = [RobotStream(robot_id=rid, intrinsics=plan.intrinsics, stamps_s=plan.stamps_s, images=rgbs[k],
                          T_world_cam=plan.T_world_cam[k], depth=depths[k], depth_units_per_m=1.0,
                          frame_ids=[f"{s:.6f}" for s in plan.stamps_s]) for k, rid in enumerate(plan.robot_ids)]
    va = np.stack([viewing_angle_matrix(list(plan.T_world_cam[:, t])) for t in range(T)])
    meta = {"world": world, "seed": seed, "index": index, "plan": plan.meta, "viewing_angle_rad": va,
            "transition": has_transition(ov), "conf": c}
    return Encounter(name=plan.name, robots=robots, overlap=ov, meta=meta)


# --------------------------------------------------------------------------- files
def _atomic_write(path: Path, data: bytes | str) -> None:
    """Atomic, not flushed to disk: the whole suite folder is renamed into place at the end."""
    atomic_write_bytes(path, data.encode() if isinstance(data, str) else data, durable=False)


def _write_png(path: Path, img: np.ndarray) -> None:
    import cv2

    ok, buf = cv2.imencode(".png", img)
    if not ok:
        raise SynthError(f"cannot encode PNG {path}")
    _atomic_write(path, buf.tobytes())


def depth_to_png_units(depth_m: np.ndarray, units_per_m: int = DEPTH_UNITS_PER_M) -> np.ndarray:
    """Metres -> uint16 units; 0 stays 0 and values beyond the uint16 range become 0 (unknown)."""
    d = np.rint(np.asarray(depth_m, np.float64) * units_per_m)
    d[(d > 65535) | ~np.isfinite(d) | (d < 0)] = 0
    return d.astype(np.uint16)


def _camera_yaml(plan: EncounterPlan) -> str:
    K = plan.intrinsics
    return (f"# pinhole, no distortion (rendered by cerpe synth, {plan.world})\n"
            f"width: {K.width}\nheight: {K.height}\nfx: {K.fx:.6f}\nfy: {K.fy:.6f}\ncx: {K.cx:.6f}\ncy: {K.cy:.6f}\n"
            f"distortion: [0.0, 0.0, 0.0, 0.0, 0.0]\n")


def _tum(stamps: np.ndarray, T_world_cam: np.ndarray) -> str:
    from ..tum import format_tum

    return format_tum(stamps, T_world_cam, stamp_decimals=6,
                      header="timestamp tx ty tz qx qy qz qw  (camera-to-world, OpenCV camera axes)")


def write_encounter(world: str, conf: dict, index: int, root: Path) -> tuple[str, int, bool]:
    """Render encounter ``index`` into ``root/<name>/``; its ``meta.json`` is written last.

    Returns ``(name, n_frames_rendered, overlap_transition)``.
    """
    plan = plan_for(world, conf, index)
    enc = root / plan.name
    if (enc / "meta.json").is_file():  # finished in an interrupted earlier run
        meta = json.loads((enc / "meta.json").read_text())
        return plan.name, 0, bool(meta.get("overlap_transition", False))
    n, T = len(plan.robot_ids), plan.n_steps
    for rid in plan.robot_ids:
        (enc / rid / "rgb").mkdir(parents=True, exist_ok=True)
        (enc / rid / "depth").mkdir(parents=True, exist_ok=True)
    ov = np.zeros((T, n, n), np.float32)
    for t, rr, dd in iter_frames(plan):
        stamp = f"{plan.stamps_s[t]:.6f}"
        for k, rid in enumerate(plan.robot_ids):
            _write_png(enc / rid / "rgb" / f"{stamp}.png", rr[k][:, :, ::-1])
            _write_png(enc / rid / "depth" / f"{stamp}.png", depth_to_png_units(dd[k]))
        ov[t] = overlap_matrix(dd, [plan.intrinsics] * n, list(plan.T_world_cam[:, t]), conf["overlap_stride"])
    for k, rid in enumerate(plan.robot_ids):
        _atomic_write(enc / rid / "groundtruth.txt", _tum(plan.stamps_s, plan.T_world_cam[k]))
        _atomic_write(enc / rid / "camera.yaml", _camera_yaml(plan))
    buf = io.BytesIO()
    np.save(buf, ov)
    _atomic_write(enc / "overlap.npy", buf.getvalue())
    va = np.stack([viewing_angle_matrix(list(plan.T_world_cam[:, t])) for t in range(T)])
    trans = has_transition(ov)
    if not trans:
        log.warning("%s: overlap never crosses both 0.3 and 0.05 for any robot pair", plan.name)
    meta = {"name": plan.name, "world": world, "seed": conf["seed"], "index": index, "robot_ids": plan.robot_ids,
            "stamps_s": [round(float(s), 6) for s in plan.stamps_s], "plan": plan.meta,
            "overlap_transition": bool(trans), "overlap_max": float(max(ov[:, i, j].max() for i in range(n) for j in range(n) if i != j)),
            "viewing_angle_rad": np.round(va, 6).tolist(),
            "depth_note": "depth PNG: uint16 millimetres, 0 = no surface or beyond 65.535 m"}
    _atomic_write(enc / "meta.json", json.dumps(meta, indent=1))
    return plan.name, n * T, bool(trans)


def _manifest(setting: str, world: str, conf: dict, names: list[str], robots: dict[str, list[str]]) -> str:
    import yaml

    doc = {
        "name": setting,
        "adapter": "mocap",
        "enabled": True,
        "data_root": ".",
        "metric_depth": "sensor",
        "metric_depth_options": sensor_options(world),
        "sync_tolerance_s": 0.02,
        "evaluation": {"every": 1},
        "encounters": [{
            "name": e,
            "overlap": f"{e}/overlap.npy",
            "robots": [{
                "id": r, "images": f"{e}/{r}/rgb", "trajectory": f"{e}/{r}/groundtruth.txt",
                "trajectory_format": "tum", "intrinsics": f"{e}/{r}/camera.yaml", "T_body_cam": "identity",
                "depth": f"{e}/{r}/depth", "depth_units_per_m": DEPTH_UNITS_PER_M, "interpolate": False,
            } for r in robots[e]],
        } for e in names],
    }
    head = f"# written by `cerpe synth {world}` (cerpe.synth v{SYNTH_VERSION}); see meta.json for the arguments\n"
    return head + yaml.safe_dump(doc, sort_keys=False)


def code_fingerprint() -> str:
    """Hash of the generator's source: output made by other code is not "the same arguments"."""
    import hashlib

    h = hashlib.sha256()
    for name in ("renderer", "textures", "noise", "materials_outdoor", "materials_indoor", "shaders", "worlds",
                 "plan", "cad_intersection", "indoor_team", "groundtruth", "writer"):
        h.update((Path(__file__).parent / f"{name}.py").read_bytes())
    return h.hexdigest()[:16]


def _cache_key(world: str, conf: dict) -> dict:
    key = {k: v for k, v in conf.items() if k != "workers"}
    key["size"] = list(key["size"])
    return {"generator": "cerpe.synth", "version": SYNTH_VERSION, "code": code_fingerprint(), "world": world,
            "args": key}


def _worker_init() -> None:
    import cv2

    cv2.setNumThreads(1)  # one process per core already


@contextmanager
def _main_not_rerun():
    """While starting spawned workers, hide a ``__main__`` script's path so children do not run it."""
    main = sys.modules.get("__main__")
    path = getattr(main, "__file__", None)
    if main is None or path is None or getattr(main, "__spec__", None) is not None:
        yield
        return
    del main.__file__
    try:
        yield
    finally:
        main.__file__ = path


def _render_parallel(jobs: list[tuple], workers: int, bar) -> list[tuple[str, int, bool]]:
    """Render ``jobs`` in ``workers`` spawned processes; ``[]`` if processes cannot be started.

    Spawn, not fork: a forked child inherits the parent's OpenCV/BLAS thread pools in a
    broken state and can hang. Spawn would re-run a calling *script*
    (an unguarded one would render again in every child); the jobs only need
    :mod:`cerpe.synth.writer`, so the script path is hidden while the workers start.
    If processes still cannot start, everything is rendered in this process (logged).
    """
    import multiprocessing as mp

    results = []
    try:
        with _main_not_rerun():
            pool = mp.get_context("spawn").Pool(min(workers, len(jobs)), initializer=_worker_init)
        with pool:
            for r in pool.imap_unordered(_render_job, jobs):
                results.append(r)
                bar.update(r[1])
    except RuntimeError as exc:
        if results:
            raise
        log.warning("cannot start worker processes (%s); rendering in this process", str(exc).strip().splitlines()[0])
    return results


def _render_job(job: tuple) -> tuple[str, int, bool]:
    world, conf, index, root = job
    return write_encounter(world, conf, index, Path(root))


@contextmanager
def suite_lock(out: Path):
    """Hold an exclusive lock on the suite folder ``out`` (``.<name>.lock`` beside it) while inside.

    Two processes asked for the same suite (two robots started on one host from one
    synthetic manifest, or ``cerpe bench`` beside ``make paper``) would otherwise render
    into the same ``.partial`` folder. The second now waits for the first and then finds
    the suite made. The lock is released when its holder exits, even by a crash (``flock``).
    """
    import fcntl

    lock_path = out.with_name(f".{out.name}.lock")
    try:
        fh = open(lock_path, "a+")
    except OSError as exc:  # a folder this user may not write into (read-only, /proc ...)
        raise SynthError(f"synth output folder {out}: cannot write into {out.parent}: {exc.strerror or exc}") from None
    with fh:
        try:
            fcntl.flock(fh, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            log.info("%s: another process is rendering it; waiting (lock %s)", out, lock_path)
            t0 = time.perf_counter()
            fcntl.flock(fh, fcntl.LOCK_EX)
            log.info("%s: waited %.0f s for the other process", out, time.perf_counter() - t0)
        try:
            yield
        finally:
            fcntl.flock(fh, fcntl.LOCK_UN)


def generate_suite(world: str, out_dir: str | Path, conf: dict | None = None, *, force: bool = False,
                   progress: bool = True, setting: str | None = None) -> Path:
    """Render ``conf["n_encounters"]`` encounters of ``world`` into ``out_dir``; return its manifest path.

    Same arguments as an existing ``out_dir/meta.json`` -> nothing is rendered.
    Different arguments -> :class:`SynthError` unless ``force`` (then it is replaced).
    Processes asking for the same ``out_dir`` at once take turns (:func:`suite_lock`).
    """
    if world not in WORLDS:
        raise SynthError(f"unknown world {world!r}; known worlds: {', '.join(WORLDS)}")
    c = full_conf(world, conf)
    out = Path(out_dir)
    try:
        ensure_dir(out, "synth output folder", create=False)
        ensure_dir(out.parent, "parent of the synth output folder")
    except AtomicIOError as exc:
        raise SynthError(str(exc)) from None
    with suite_lock(out):
        return _generate_locked(world, c, out, force, progress, setting or SETTING_OF_WORLD[world])


def _generate_locked(world: str, c: dict, out: Path, force: bool, progress: bool, setting: str) -> Path:
    key = _cache_key(world, c)
    if out.exists():
        meta = out / "meta.json"
        try:
            old = json.loads(meta.read_text()) if meta.is_file() else None
        except json.JSONDecodeError:
            old = None
        if old is not None and old.get("key") == key and (out / "manifest.yaml").is_file():
            log.info("%s: up to date (same generator arguments); nothing rendered", out)
            return out / "manifest.yaml"
        if old is None and any(out.iterdir()):
            # never delete a folder we did not write, --force or not
            raise SynthError(f"{out} exists and is not a cerpe synth output (no {meta.name} with a generator key); "
                             f"choose another --out")
        if not force:
            what = ("by another version of the generator code" if {**old.get("key", {}), "code": key["code"]} == key
                    else "with different arguments")
            raise SynthError(f"{out} was generated {what} ({meta}); use --force (force=True) "
                             f"to replace it, or another --out")
    tmp = out.with_name(f".{out.name}.partial")
    if tmp.exists():
        try:
            same = json.loads((tmp / "key.json").read_text()) == key
        except (OSError, json.JSONDecodeError):
            same = False
        if not same:
            shutil.rmtree(tmp)
    ensure_dir(tmp, "synth work folder")
    _atomic_write(tmp / "key.json", json.dumps(key))
    jobs = [(world, c, i, str(tmp)) for i in range(c["n_encounters"])]
    total = sum((max(c["n_robots"], 3) if world == "cad-intersection" and i >= c["n_encounters"] - c["n_three"]
                 else c["n_robots"]) * c["n_frames"] for i in range(c["n_encounters"]))
    from tqdm import tqdm

    bar = tqdm(total=total, desc=f"synth {setting}", unit="frame", disable=not progress)
    results = []
    if c["workers"] > 1 and len(jobs) > 1:
        results = _render_parallel(jobs, c["workers"], bar)
    if not results:
        for j in jobs:
            results.append(_render_job(j))
            bar.update(results[-1][1])
    bar.close()
    names = [encounter_name(world, c["seed"], i) for i in range(c["n_encounters"])]
    robots = {e: json.loads((tmp / e / "meta.json").read_text())["robot_ids"] for e in names}
    _atomic_write(tmp / "manifest.yaml", _manifest(setting, world, c, names, robots))
    trans = {name: t for name, _, t in results}
    _atomic_write(tmp / "meta.json", json.dumps({"key": key, "setting": setting, "encounters": names,
                                                 "overlap_transition": trans}, indent=1))
    (tmp / "key.json").unlink()
    if out.exists():
        shutil.rmtree(out)
    os.replace(tmp, out)
    return out / "manifest.yaml"


def generate_suites(name: str, out_root: str | Path, *, force: bool = False, progress: bool = True) -> dict[str, Path]:
    """Render the named suite (``fixture`` | ``paper-default``): one setting folder per world
    under ``out_root``; returns ``{setting_name: manifest_path}``."""
    if name not in SUITES:
        raise SynthError(f"unknown suite {name!r}; known suites: {', '.join(SUITES)}")
    return {setting: generate_suite(world, Path(out_root) / setting, conf, force=force, progress=progress,
                                    setting=setting)
            for setting, (world, conf) in SUITES[name].items()}

"""Run ONE robot of a team online and write its run folder (what ``cerpe online`` does).

Three ways, one node (:class:`~cerpe.online.node.RobotNode`):

* ``input: ros``: the robot's own ROS 2 topics (:class:`~cerpe.online.ros_input.RosInput`), by stamps;
  the roster is ``robots`` or a manifest's encounter, whose ground truth (if any) is then looked up at
  each frame's stamp;
* ``input: manifest``: a replay of the robot's frames of a manifest encounter by their stamps, in real
  time (``speed`` 1) or faster (:class:`~cerpe.online.sources.ManifestReplay`);
* ``input: manifest`` with the link's ``sync: lockstep``: the team's step, which reproduces ``cerpe run``.

The run folder is :mod:`cerpe.runfolder`'s with only this robot as ego, plus ``online.json`` (the
node's report) and, with a manifest, ``peers_overlap.csv``. Ctrl-C (or SIGTERM) ends a run by stamps
after the frame in progress: its folder is written with the frames taken, and the robot says bye.
"""
from __future__ import annotations

import contextlib
import hashlib
import logging
import math
import signal
import tempfile
import threading
import time
from pathlib import Path
from typing import Any, Iterator, Mapping, NamedTuple

import numpy as np

from .. import knobs
from ..atomicio import atomic_write_json, atomic_write_text, ensure_dir
from ..config import merge_conf
from ..methods import CERPE_METHODS, METHOD_LABELS
from ..runfolder import write
from ..runfolder.layout import DONE_JSON, PEER_OVERLAP_CSV, RunError
from ..runfolder.provenance import code_hash, config_dict
from . import ros, zenoh_session, zenoh_wire
from .live import LiveEncounter, ReplayEncounter
from .node import OnlineError, RobotNode
from .zenoh_link import ZenohLink
from .zenoh_link import default_conf as link_defaults

log = logging.getLogger(__name__)

INPUTS = ("manifest", "ros")


class OnlineRun(NamedTuple):
    """What :func:`run_online` did: the run folder, the encounter, the peers this robot met."""

    out: Path
    encounter: str
    peers_met: list[str]


def _encounter(setting: Any, name: str | None, manifest: Path) -> Any:
    names = [e.name for e in setting.encounters]
    if name is None:
        if len(names) != 1:
            raise OnlineError(f"{manifest} has {len(names)} encounters {names}: choose one with --encounter")
        return setting.encounters[0]
    for enc in setting.encounters:
        if enc.name == name:
            return enc
    raise OnlineError(f"{manifest}: no encounter {name!r}; it has {names}")


@contextlib.contextmanager
def _machine_lock(manifest: Path) -> Iterator[None]:
    """Serialise loading ``manifest`` between the robot processes of one machine.

    A synthetic manifest renders its suite into a shared cache on first load; two
    robots started together would otherwise render into the same folder at once.
    """
    try:
        import fcntl
    except ImportError:  # not POSIX: no lock (start the robots one after the other there)
        yield
        return
    key = hashlib.sha1(str(manifest).encode()).hexdigest()[:16]
    path = Path(tempfile.gettempdir()) / f"cerpe-online-{key}.lock"
    with open(path, "a+") as fh:
        fcntl.flock(fh, fcntl.LOCK_EX)
        try:
            yield
        finally:
            fcntl.flock(fh, fcntl.LOCK_UN)


@contextlib.contextmanager
def _stop_on_signals(stop: Any) -> Iterator[None]:
    """Ctrl-C and SIGTERM call ``stop()`` (the run ends after its frame); a second Ctrl-C interrupts."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    old = {sig: signal.getsignal(sig) for sig in (signal.SIGINT, signal.SIGTERM)}

    def handler(signum: int, _frame: Any) -> None:
        log.warning("%s: ending the run after this frame (again to interrupt)", signal.Signals(signum).name)
        signal.signal(signal.SIGINT, old[signal.SIGINT])
        stop()

    for sig in old:
        signal.signal(sig, handler)
    try:
        yield
    finally:
        for sig, h in old.items():
            signal.signal(sig, h)


def peers_overlap_csv(enc: Any, robot: str) -> str:
    """``encounter, step, ego, other, overlap_gt`` of the pairs (peer, ``robot``): the overlap ground truth
    of the rows this robot's peers write about it, which its own success after co-visibility needs."""
    k = enc.robot_ids.index(robot)
    lines = ["encounter,step,ego,other,overlap_gt"]
    for j, peer in enumerate(enc.robot_ids):
        if j == k:
            continue
        for t in range(enc.n_steps):
            ov = float(enc.overlap[t, j, k]) if enc.overlap is not None else math.nan
            lines.append(f"{enc.name},{t},{peer},{robot},{'' if math.isnan(ov) else f'{ov:.9g}'}")
    return "\n".join(lines) + "\n"


def _roster(enc: Any, robots: list[str] | None, robot: str, manifest: Path | None) -> list[str]:
    ids = list(enc.robot_ids) if enc is not None else list(robots or [])
    if enc is None and not ids:
        raise OnlineError("--input ros needs the team's roster: --robots r0,r1,... (or --manifest)")
    if enc is not None and robots and list(robots) != ids:
        raise OnlineError(f"--robots {','.join(robots)} differs from the roster {ids} of {manifest}")
    if robot not in ids:
        where = f"encounter {enc.name} of {manifest} has robots" if enc is not None else "--robots lists"
        raise OnlineError(f"--robot {robot!r}: {where} {ids}")
    return ids


REGISTRATIONS = ("worker", "inline")


def _registration_report(registrar: Any, agent: Any) -> dict[str, Any]:
    """What the robot's registrar did (empty when it registers in the step): its counts (submitted,
    done, failed, dropped, worker restarts) and how late the landed estimates were, in steps and seconds."""
    if registrar is None:
        return {}
    late = agent.s.registration_lateness
    steps = [s for s, _ in late]
    secs = [t for _, t in late]

    def q(xs: list, p: float) -> float | None:
        return float(np.percentile(xs, p)) if xs else None

    return {**registrar.stats(), "landed": len(late), "late_steps_median": q(steps, 50), "late_steps_p90": q(steps, 90),
            "late_s_median": q(secs, 50), "late_s_p90": q(secs, 90)}


def run_online(manifest: Path | str | None, encounter: str | None, robot: str, out: Path | str, *,
               link_conf: Mapping[str, Any] | None = None, node_conf: Mapping[str, Any] | None = None,
               method: str = "cerpe", preset: str = "paper", seed: int = 0, overwrite: bool = False,
               progress: bool = True, setting: Any = None, plugins: Any = None, config: Any = None,
               sets: Mapping[str, Any] | None = None, input: str = "manifest", robots: list[str] | None = None,
               speed: float = 1.0, use_odometry: bool = False, ros_input: Mapping[str, Any] | None = None,
               stall_s: float = 2.0, registration: str = "worker") -> OnlineRun:
    """Run robot ``robot`` online and write its run folder ``out`` (see the module docstring).

    ``link_conf``: options of :class:`~cerpe.online.zenoh_link.ZenohLink` (team, endpoints, mode,
    scouting, ``sync``); ``node_conf``: of :class:`~cerpe.online.node.RobotNode` (waits, ROS keys, TF);
    ``ros_input``: of :class:`~cerpe.online.ros_input.RosInput` (topics). ``registration``: ``worker``
    registers a received image on a worker thread, its estimate landing when ready (by stamps only;
    lock-step registers in the step, as ``cerpe run``), ``inline`` in the step. ``setting``, ``plugins`` (an
    object with ``descriptor``, ``backbone``, ``depth``) and ``config`` may be given instead of being
    loaded (tests, embedding). Raises a :class:`~cerpe.errors.CerpeError` naming the argument, file or
    endpoint at fault. A robot that never met any peer is logged as a warning (``peers_met`` empty).
    """
    from ..algorithm import AlgorithmConfig, RobotAgent, WorkerRegistrar
    from ..pipeline.cerpe_method import cerpe_plugins_and_config
    from ..pipeline.setting import load_manifest_setting

    if method not in CERPE_METHODS:
        raise OnlineError(f"--method {method!r}: online runs support {list(CERPE_METHODS)}")
    if input not in INPUTS:
        raise OnlineError(f"--input {input!r}: expected one of {INPUTS}")
    if registration not in REGISTRATIONS:
        raise OnlineError(f"--registration {registration!r}: expected one of {REGISTRATIONS}")
    lconf, nconf = merge_conf(link_defaults, link_conf, "zenoh link conf"), dict(node_conf or {})
    if input == "manifest":  # a replay's stamps are the dataset's: one clock, nothing to map
        lconf["clock_tolerance_s"] = float("inf")
    zenoh_wire.check_chunk(lconf["team"], "--team")
    zenoh_wire.Wire(lconf["sync"])
    zenoh_session.zenoh_config({k: lconf[k] for k in zenoh_session.default_conf})  # bad options fail now
    ros.check_distro((nconf.get("ros") or {}).get("distro", ros.default_conf["distro"]))
    lockstep = lconf["sync"] == "lockstep"
    if lockstep and input != "manifest":
        raise OnlineError("--lockstep replays a manifest (--input manifest): live input runs by stamps")
    if not speed >= 0:
        raise OnlineError(f"--speed must be >= 0, got {speed}")
    if manifest is None and (input == "manifest" or setting is not None):
        raise OnlineError("--input manifest needs --manifest")
    manifest = None if manifest is None else Path(manifest).resolve()
    if setting is None and manifest is not None:
        with _machine_lock(manifest):
            setting = load_manifest_setting(manifest)
    enc = None if setting is None else _encounter(setting, encounter, manifest)
    roster = _roster(enc, robots, robot, manifest)
    out = Path(out)
    name = enc.name if enc is not None else "live"
    done = out / name / DONE_JSON
    if done.exists() and not overwrite:
        raise RunError(f"{done}: this robot already finished encounter {name}; use --overwrite to run it again")
    ensure_dir(write.check_out(out), "--out")  # before the link opens: an --out that cannot be written fails now
    link = ZenohLink(robot, roster, lconf)  # opens now: a bad endpoint fails before models load
    source: Any = None
    registrar: Any = None
    try:
        if input == "ros":
            from .ros_input import RosInput

            rconf = {**(ros_input or {})}
            rconf.setdefault("stall_s", stall_s)
            source = RosInput(link.session, robot, rconf, seed)
        # live: the depth topic's depth as it is (a dataset's); a replay: the manifest's source
        depth_kind = ("dataset" if "depth" in source.topics else "none") if input == "ros" else setting.metric_depth
        if plugins is None:
            plugins, config, mconf = cerpe_plugins_and_config(
                method, depth_kind, getattr(setting, "metric_depth_options", None), preset, dict(sets) if sets else None)
        else:
            config = config if config is not None else AlgorithmConfig()
            mconf = {"tree": config_dict(knobs.as_dict(config)), "preset": "given", "plugins": "given"}
        k = roster.index(robot)
        if registration == "worker" and not lockstep:
            registrar = WorkerRegistrar(plugins.backbone)
        agent = RobotAgent(robot, k, config, plugins.descriptor, plugins.backbone, plugins.depth, registrar)
        node = RobotNode(agent, link, roster, conf=nconf)
        if input == "manifest" and not lockstep:
            from .sources import ManifestReplay

            odo = enc.meta.get("odometry", {}).get(robot) if use_odometry else None
            if use_odometry and odo is None:
                raise OnlineError(f"--use-odometry: {manifest} gives no odometry of robot {robot} (the rosbag "
                                  f"adapter's odometry_topic)")
            source = ManifestReplay(enc.robots[k], speed, seed, odo, stall_s)
    except BaseException:
        if source is not None and hasattr(source, "close"):
            source.close()
        if registrar is not None:
            registrar.close()
        link.close(0.0)
        raise
    run_conf = {"method": method, "preset": preset, "seed": int(seed), "setting": getattr(setting, "name", "live"),
                "encounters": [name], "method_config": mconf, "code": code_hash(method),
                "online": {"robot": robot, "team": link.team, "robots": list(roster), "input": input,
                           "link": config_dict(link.conf), "node": config_dict(node.conf),
                           "speed": float(speed), "registration": "inline" if registrar is None else "worker",
                           "ros_input": config_dict(dict(getattr(source, "conf", {}) or {}))}}
    record = {"method": method, "label": METHOD_LABELS[method] + " (online)",
              "metric_scale": depth_kind != "none", "manifest": str(manifest) if manifest else None,
              "seed": int(seed), "preset": preset, "setting": getattr(setting, "name", "live"), "zenoh_id": link.zid}
    try:
        folder = write.open_run(out, run_conf, record, overwrite=overwrite)
    except BaseException:
        if hasattr(source, "close"):
            source.close()
        if registrar is not None:
            registrar.close()
        link.close(0.0)
        raise
    with folder, node:
        if enc is not None:
            atomic_write_text(out / name / PEER_OVERLAP_CSV, peers_overlap_csv(enc, robot))
        t0 = time.perf_counter()
        if lockstep:
            stream = enc.robots[k]

            def frames() -> Iterator[tuple]:
                from ..protocols import FrameContext

                for t in range(enc.n_steps):
                    yield stream.image(t), FrameContext(robot, t, stream.intrinsics, stream.depth_m(t), seed), \
                        float(stream.stamps_s[t])

            folder.write_encounter(enc, lambda _enc: node.run(frames()), progress=progress)
        else:
            target = LiveEncounter(name, roster, enc) if input == "ros" else ReplayEncounter(enc)

            def steps(_enc: Any) -> Iterator[Any]:
                for res in node.run_stamps(source, wait_for_team=input == "manifest"):
                    if input == "ros":
                        target.note(res.step, res.robots[0].stamp_s)
                    yield res

            with _stop_on_signals(source.stop):
                try:
                    folder.write_encounter(target, steps, progress=progress)
                finally:
                    if hasattr(source, "close"):
                        source.close()
                    if registrar is not None:
                        registrar.close()
        report = {**node.report(), "wall_time_s": time.perf_counter() - t0,
                  "input": dict(source.stats) if source is not None else {},
                  "registration": _registration_report(registrar, agent)}
        atomic_write_json(out / name / "online.json", report)
        lost = {k: v for k, v in node.stats.items() if ":" in k}
        log.info("robot %s: %d steps, degradations %s", robot, report["n_steps"], lost or "none")
        if not node.met:
            log.warning("robot %s never met any of its peers %s (team %r): its run holds no inter-robot estimate; "
                        "check --team, the endpoints (--connect / --listen) and that the peers were started",
                        robot, list(node.peers), link.team)
    return OnlineRun(out, name, sorted(node.met))

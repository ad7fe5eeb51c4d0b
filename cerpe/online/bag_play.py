"""A bag's topics published on Zenoh as a robot's ROS 2 graph would (``cerpe bag play``): live mode without a robot.

Every message of the chosen topics goes out at its bag time against the wall clock (``rate`` 1: real
time; 0.5: half speed), CDR on the key of ``rmw_zenoh`` (with its attachment) or of
``zenoh-bridge-ros2dds``, like ``ros2 bag play`` on that middleware; header stamps are left as
recorded. ROS 1 bags are converted message by message (the standard types). For robot ``robot``: a
bag that has topics under ``/<robot>/`` (a team's bag) plays those; any other bag plays all its
topics under the namespace ``/<robot>`` (``namespace`` overrides both; ``/``: as they are), which is
where ``cerpe online --robot <robot> --input ros`` looks by default.
"""
from __future__ import annotations

import logging
import os
import time
from typing import Any, Mapping, Sequence

from ..errors import CerpeError
from ..rosio import types as rt
from ..rosio.bags import BagReader, BagTruncated
from . import ros

log = logging.getLogger(__name__)


class BagPlayError(CerpeError, ValueError):
    """A bag or option that cannot be played (names the topic or option)."""


def plan(topics: Mapping[str, str], robot: str, namespace: str | None, wanted: Sequence[str] | None,
         ros1: bool) -> dict[str, str]:
    """bag topic -> the topic it is published on (see the module docstring); a :class:`BagPlayError` for a
    wanted topic the bag does not hold."""
    missing = [t for t in wanted or () if t not in topics]
    if missing:
        raise BagPlayError(f"--topics {', '.join(missing)}: not in the bag; it holds "
                           f"{', '.join(f'{t} ({k})' for t, k in sorted(topics.items()))}")
    own = [t for t in topics if t.startswith(f"/{robot}/")]
    chosen = list(wanted) if wanted else (own or list(topics))
    if ros1:
        store = rt.typestore().types
        unknown = [t for t in chosen if topics[t] not in store]
        if unknown:
            log.warning("not played (ROS 1 types without a ROS 2 counterpart here): %s", ", ".join(unknown))
            chosen = [t for t in chosen if t not in unknown]
    if not chosen:
        raise BagPlayError("no topic of the bag can be played")
    if namespace is None:
        namespace = "/" if own and not wanted else f"/{robot}"
    ns = "/" + namespace.strip("/")
    return {t: (t if ns == "/" or t.startswith(ns + "/") else f"{ns.rstrip('/')}{t}") for t in chosen}


def play(path: Any, robot: str, session: Any, ros_conf: Mapping[str, Any], rate: float = 1.0,
         namespace: str | None = None, topics: Sequence[str] | None = None, start_at: float | None = None) -> dict:
    """Publish the bag ``path`` for ``robot`` on ``session`` (keys as ``ros_conf``: key_format, domain_id, distro);
    returns counts per published topic. ``start_at``: the wall time (``time.time()``) of its first message."""
    if not rate > 0:
        raise BagPlayError(f"--rate must be > 0, got {rate}")
    counts: dict[str, int] = {}
    with BagReader(path, "bag") as bag:
        out = plan(bag.topics, robot, namespace, topics, bag.ros1)
        kinds = bag.topics
        pubs, seq, gid = {}, {}, {t: os.urandom(16) for t in out}
        for t, name in out.items():
            pubs[t] = session.declare_publisher(ros.zenoh_key(name, ros_conf, kinds[t]))
            seq[t] = 0
        log.info("playing %s for robot %s: %s", path, robot, ", ".join(f"{t} -> {n}" for t, n in out.items()))
        w0, t0 = (time.time() if start_at is None else float(start_at)), None
        try:
            for topic, _, t_ns, cdr in bag.messages(out, cdr=True):
                t0 = t_ns if t0 is None else t0
                delay = w0 + (t_ns - t0) * 1e-9 / rate - time.time()
                if delay > 0:
                    time.sleep(delay)
                seq[topic] += 1
                if ros_conf["key_format"] == "rmw_zenoh":
                    pubs[topic].put(cdr, attachment=ros.rmw_attachment(seq[topic], time.time_ns(), gid[topic]))
                else:
                    pubs[topic].put(cdr)
                counts[out[topic]] = counts.get(out[topic], 0) + 1
        except BagTruncated as exc:
            log.warning("%s; stopped after %d messages", exc, exc.n_read)
        finally:
            for p in pubs.values():
                p.undeclare()
    return counts

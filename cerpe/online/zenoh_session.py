"""Opening a Zenoh session from cerpe's options (mode, endpoints, scouting), with one clear error.

Options (``default_conf``; ``cerpe online`` maps ``--connect``/``--listen``/... onto them):

* ``mode``: ``peer`` (default; robots talk directly) or ``client`` (through a
  Zenoh router, e.g. ``zenohd`` or ROS 2's ``rmw_zenohd``, given in ``connect``);
* ``connect``/``listen``: Zenoh endpoints such as ``tcp/10.0.0.2:7447``; a peer
  may also ``connect`` to a router (optional) to reach robots beyond the LAN;
* ``multicast_scouting``: find peers on the LAN by UDP multicast (default on;
  turn it off and give endpoints where multicast does not pass);
* ``zenoh``: further Zenoh settings ``{json5 path: value}``, applied last.

A peer whose ``connect`` endpoint is not up yet keeps retrying in the
background (robots start in any order). A client whose router cannot be
reached, an endpoint that does not parse, or a ``listen`` address that is not
this machine's fails at once with :class:`ZenohSessionError`.
"""
from __future__ import annotations

import json
from typing import Any, Mapping

from ..errors import CerpeError

default_conf: dict[str, Any] = {
    "mode": "peer",               # "peer" or "client" (needs a router in "connect")
    "connect": [],                # Zenoh endpoints to dial, e.g. ["tcp/10.0.0.2:7447"]
    "listen": [],                 # endpoints to listen on; [] = Zenoh's default (peer: any port)
    "multicast_scouting": True,   # find peers on the LAN by UDP multicast
    "zenoh": None,                # extra Zenoh config, {json5 path: value}, applied last
}

MODES = ("peer", "client")


class ZenohSessionError(CerpeError, ValueError):
    """A bad session option, or a Zenoh session that cannot open."""


def first_line(exc: BaseException) -> str:
    """A Zenoh error's message without the Rust source location it carries."""
    text = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
    return text.split(" at /")[0]


def zenoh_config(conf: Mapping[str, Any]) -> Any:
    """A ``zenoh.Config`` from the options of :data:`default_conf` (all keys present)."""
    import zenoh

    if conf["mode"] not in MODES:
        raise ZenohSessionError(f"zenoh mode {conf['mode']!r}: expected one of {MODES}")
    entries: list[tuple[str, Any]] = [("mode", conf["mode"]),
                                      ("scouting/multicast/enabled", bool(conf["multicast_scouting"]))]
    for what in ("connect", "listen"):
        eps = conf[what]
        if isinstance(eps, str) or not all(isinstance(e, str) for e in eps):
            raise ZenohSessionError(f"--{what}: expected a list of endpoints like tcp/10.0.0.2:7447, got {eps!r}")
        if eps:
            entries.append((f"{what}/endpoints", list(eps)))
    if conf["mode"] == "client" and not conf["connect"]:
        raise ZenohSessionError("zenoh mode 'client' needs a router endpoint in --connect (e.g. tcp/10.0.0.1:7447)")
    extra = conf.get("zenoh") or {}
    if not isinstance(extra, Mapping):
        raise ZenohSessionError(f"zenoh options: expected {{json5 path: value}}, got {type(extra).__name__}")
    zc = zenoh.Config()
    for key, value in entries + list(extra.items()):
        try:
            zc.insert_json5(str(key), json.dumps(value))
        except zenoh.ZError as exc:
            raise ZenohSessionError(f"zenoh config {key} = {value!r}: {first_line(exc)}") from None
    return zc


def open_session(conf: Mapping[str, Any], who: str) -> Any:
    """Open a ``zenoh.Session`` for ``who`` (e.g. ``"robot r0"``); one clear error if it cannot."""
    import zenoh

    zc = zenoh_config(conf)
    try:
        return zenoh.open(zc)
    except zenoh.ZError as exc:
        raise ZenohSessionError(
            f"{who}: Zenoh session cannot open (mode {conf['mode']}, listen {list(conf['listen']) or 'default'}, "
            f"connect {list(conf['connect']) or 'none'}): {first_line(exc)}") from None

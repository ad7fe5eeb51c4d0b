"""TCP transport between robot processes: length-prefixed frames, one connection per peer pair.

Why TCP only (and not UDP for the small broadcasts): image replies are 60-100 KB,
far above one UDP datagram, so TCP is needed anyway; with two or three robots a
"broadcast" is two unicasts on connections that already exist, and one ordered
stream per pair gives a property the runner relies on: once a frame of step
``t+1`` has arrived from a peer, nothing of step ``t`` can still come from it,
so a robot never waits for a frame that cannot arrive. Stdlib sockets only.

Envelope (little endian) around each :mod:`cerpe.messages` frame::

    magic b"CN"  2 B | type u8 (1 hello, 2 message, 3 bye) | length u32 | payload

Communication figures count the *message* frame bytes exactly like
:class:`cerpe.transport.Channel` (a broadcast once for its sender); the bytes this
transport really writes (one copy per peer, plus 7-byte envelopes and hellos) are
kept separately in :attr:`NetTransport.stats` (``wire_bytes_<kind>``).

Connections: the robot whose id sorts first dials, the other accepts; both send
a hello (JSON ``{"proto": 1, "robot": id}``) and check the other's. A dialer
retries with exponential backoff until the transport closes (a peer that is not
up yet, or that restarts). Faults never raise out of the transport; they become
events for the runner and counters in :attr:`stats`:

* a message frame that does not decode -> ``("garbled", peer, why)``;
* a broken envelope (bad magic, oversize length): the stream cannot be
  re-synchronised -> ``garbled`` and the connection is closed (the dialer redials);
* a connection that ends without a bye -> ``("down", peer, why)``; a bye ->
  ``("bye", peer, "")``; a (re)connection -> ``("up", peer, "")``;
* a connection that does not say a valid hello -> counted ``bad_hello``, closed.
"""
from __future__ import annotations

import json
import logging
import socket
import struct
import threading
import time
from collections import Counter
from dataclasses import dataclass
from typing import Any, Mapping

from ..errors import CerpeError
from ..messages import MessageError, decode

log = logging.getLogger(__name__)

ENVELOPE = struct.Struct("<2sBI")
ENVELOPE_MAGIC = b"CN"
T_HELLO, T_MSG, T_BYE = 1, 2, 3
PROTO = 1
# message type byte (cerpe.messages header offset 3) -> kind, as cerpe.transport.KINDS names them
KIND_OF_TYPE: dict[int, str] = {1: "descriptor", 2: "pose", 3: "request", 4: "reply"}

default_conf: dict[str, Any] = {
    "backoff_initial_s": 0.05,   # first redial delay; doubles per failure
    "backoff_max_s": 2.0,        # ... up to this
    "dial_timeout_s": 2.0,       # TCP connect
    "hello_timeout_s": 5.0,      # a connection must say hello within this
    "send_timeout_s": 10.0,      # a blocked send (peer stopped reading) closes the connection
    "max_frame_bytes": 32 << 20,  # larger length prefix = garbage stream
}


class OnlineError(CerpeError, ValueError):
    """Bad online configuration (address, robot id, port in use)."""


@dataclass(frozen=True)
class Address:
    host: str
    port: int

    def __str__(self) -> str:
        return f"[{self.host}]:{self.port}" if ":" in self.host else f"{self.host}:{self.port}"


def parse_address(text: str, what: str = "address") -> Address:
    """``HOST:PORT`` (``[v6]:PORT`` for IPv6) -> :class:`Address`; port 0 = any free port."""
    s = str(text).strip()
    host, sep, port = s.rpartition(":")
    if host.startswith("[") and host.endswith("]"):
        host = host[1:-1]
    if not sep or not host or not port.isdigit() or not (0 <= int(port) <= 65535):
        raise OnlineError(f"{what} {text!r}: expected HOST:PORT with a port in 0..65535 (e.g. 10.0.0.2:7000)")
    return Address(host, int(port))


def parse_peer(text: str) -> tuple[str, Address]:
    """``ID=HOST:PORT`` -> ``(id, address)``."""
    rid, sep, addr = str(text).partition("=")
    if not sep or not rid.strip():
        raise OnlineError(f"--peer {text!r}: expected ROBOT_ID=HOST:PORT (e.g. r1=10.0.0.2:7000)")
    return rid.strip(), parse_address(addr, f"--peer {rid.strip()}")


def resolve(addr: Address, what: str) -> None:
    """Fail early, naming ``what``, when ``addr``'s host name does not resolve."""
    try:
        socket.getaddrinfo(addr.host, addr.port, type=socket.SOCK_STREAM)
    except socket.gaierror as exc:
        raise OnlineError(f"{what} {addr}: host does not resolve ({exc.strerror})") from None


def pack(ftype: int, payload: bytes) -> bytes:
    """One envelope: header + payload."""
    return ENVELOPE.pack(ENVELOPE_MAGIC, ftype, len(payload)) + payload


def hello_payload(robot_id: str) -> bytes:
    return json.dumps({"proto": PROTO, "robot": robot_id}).encode()


class _Garbage(Exception):
    """A stream that no longer parses as envelopes."""


def _recv_exact(sock: socket.socket, n: int, stop: threading.Event) -> bytes | None:
    """``n`` bytes, or None at end of stream / when ``stop`` is set; socket timeouts just poll ``stop``."""
    buf = bytearray()
    while len(buf) < n:
        if stop.is_set():
            return None
        try:
            chunk = sock.recv(min(n - len(buf), 1 << 20))
        except socket.timeout:
            continue
        if not chunk:
            return None
        buf += chunk
    return bytes(buf)


def read_envelope(sock: socket.socket, stop: threading.Event, max_bytes: int) -> tuple[int, bytes] | None:
    """Next ``(type, payload)``; None at end of stream; :class:`_Garbage` on a broken envelope."""
    head = _recv_exact(sock, ENVELOPE.size, stop)
    if head is None:
        return None
    magic, ftype, n = ENVELOPE.unpack(head)
    if magic != ENVELOPE_MAGIC or ftype not in (T_HELLO, T_MSG, T_BYE) or n > max_bytes:
        raise _Garbage(f"bad envelope (magic {magic!r}, type {ftype}, length {n})")
    body = _recv_exact(sock, n, stop)
    return None if body is None else (ftype, body)


class _Conn:
    """One established connection to a peer: a send lock and a reader thread."""

    def __init__(self, net: "NetTransport", peer: str, sock: socket.socket) -> None:
        self.net, self.peer, self.sock = net, peer, sock
        self.lock = threading.Lock()
        self.stop = threading.Event()
        self.closed = threading.Event()
        self._close_lock = threading.Lock()
        self.said_bye = False
        self.thread = threading.Thread(target=self._read_loop, name=f"cerpe-net-{net.robot_id}<-{peer}", daemon=True)

    def send(self, ftype: int, payload: bytes) -> bool:
        data = pack(ftype, payload)
        with self.lock:
            if self.closed.is_set():
                return False
            try:
                self.sock.sendall(data)
            except OSError as exc:  # timeout included: a partial frame leaves the stream unusable
                self.close(f"send failed: {exc}")
                return False
        self.net._count("wire_bytes_envelope", ENVELOPE.size)
        return True

    def _read_loop(self) -> None:
        why = "connection closed by peer"
        try:
            while not self.stop.is_set():
                got = read_envelope(self.sock, self.stop, self.net.conf["max_frame_bytes"])
                if got is None:
                    break
                ftype, body = got
                if ftype == T_BYE:
                    self.said_bye = True
                    self.send(T_BYE, b"")  # answer, so that the closing side does not see a lost peer
                    why = "bye"
                    break
                if ftype == T_MSG:
                    self.net._on_frame(self.peer, body)
                # a second hello is harmless: ignored
        except _Garbage as exc:
            self.net._event("garbled", self.peer, str(exc))
            why = f"garbage on the stream ({exc})"
        except OSError as exc:
            why = f"connection error: {exc}"
        self.close(why)

    def close(self, why: str) -> None:
        with self._close_lock:  # the reader and a failed send may both get here
            if self.closed.is_set():
                return
            # the "down" event is queued before the connection reads as closed: a runner that
            # stops waiting for this peer because it is not connected finds the event at its
            # next look (the other order lost it when the runner finished first)
            self.net._on_closed(self, why)
            self.closed.set()
        self.stop.set()
        try:
            self.sock.shutdown(socket.SHUT_RDWR)
        except OSError:
            pass
        self.sock.close()


class NetTransport:
    """This robot's end of the team network.

    Binds ``listen`` at construction (so a port in use fails at once and port 0
    gives a free port, see :attr:`address`); :meth:`connect` starts listening,
    accepting and dialing. The runner reads events with :meth:`next_events`.

    Args:
        robot_id: this robot.
        listen: where to accept connections.
        conf: overrides of :data:`default_conf`.
    """

    def __init__(self, robot_id: str, listen: Address, conf: Mapping[str, Any] | None = None) -> None:
        unknown = set(conf or {}) - set(default_conf)
        if unknown:
            raise OnlineError(f"transport conf: unknown keys {sorted(unknown)}; valid: {sorted(default_conf)}")
        self.conf = {**default_conf, **(conf or {})}
        self.robot_id = str(robot_id)
        self.peers: dict[str, Address] = {}
        self.stats: Counter[str] = Counter()
        self._cond = threading.Condition()
        self._events: list[tuple] = []
        self._conns: dict[str, _Conn] = {}
        self._closing = threading.Event()
        self._leaving = threading.Event()  # close() in progress: ends are expected
        self._finished: set[str] = set()  # peers that said bye: not redialed
        self._threads: list[threading.Thread] = []
        try:
            family = socket.AF_INET6 if ":" in listen.host else socket.AF_INET
            self._server = socket.socket(family, socket.SOCK_STREAM)
            self._server.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
            self._server.bind((listen.host, listen.port))  # a port in use fails here, before models load
            self._server.settimeout(0.2)
        except OSError as exc:
            raise OnlineError(f"--listen {listen}: cannot listen there ({exc.strerror or exc})") from None
        self.address = Address(listen.host, self._server.getsockname()[1])

    # ------------------------------------------------------------------ setup
    def connect(self, peers: Mapping[str, Address]) -> None:
        """Start accepting and dialing ``peers`` (id -> address); returns at once."""
        if self.robot_id in peers:
            raise OnlineError(f"--peer {self.robot_id}: that is this robot itself")
        self.peers = dict(peers)
        # listen only now: until then dialers are refused and retry, rather than queueing
        # connections whose hello would time out while this robot loads its models
        self._server.listen(16)
        self._spawn(self._accept_loop, "accept")
        for peer, addr in self.peers.items():
            if self._dials(peer):
                self._spawn(lambda p=peer, a=addr: self._dial_loop(p, a), f"dial-{peer}")

    def _spawn(self, fn, name: str) -> None:
        th = threading.Thread(target=fn, name=f"cerpe-net-{self.robot_id}-{name}", daemon=True)
        self._threads.append(th)
        th.start()

    def _dials(self, peer: str) -> bool:
        return self.robot_id < peer  # one connection per pair: the id that sorts first dials

    def connected(self, peer: str) -> bool:
        c = self._conns.get(peer)
        return c is not None and not c.closed.is_set()

    def wait_connected(self, timeout_s: float) -> list[str]:
        """Block until every peer is connected or ``timeout_s`` passes; returns the missing ones."""
        deadline = time.monotonic() + timeout_s
        with self._cond:
            while True:
                missing = [p for p in self.peers if not self.connected(p)]
                left = deadline - time.monotonic()
                if not missing or left <= 0:
                    return missing
                self._cond.wait(min(left, 0.2))

    # ------------------------------------------------------------------ handshake
    def _hello(self, sock: socket.socket) -> str | None:
        """Exchange hellos on a fresh socket; returns the peer id or None (counted, logged)."""
        sock.settimeout(self.conf["hello_timeout_s"])
        stop = threading.Event()
        try:
            sock.sendall(pack(T_HELLO, hello_payload(self.robot_id)))
            got = read_envelope(sock, stop, 4096)
            if got is None or got[0] != T_HELLO:
                raise _Garbage("no hello")
            info = json.loads(got[1].decode())
            peer = str(info["robot"])
            if info.get("proto") != PROTO:
                raise _Garbage(f"protocol {info.get('proto')} (this robot speaks {PROTO})")
        except (OSError, _Garbage, ValueError, KeyError, TypeError, UnicodeDecodeError) as exc:
            self._count("bad_hello")
            log.warning("robot %s: dropped a connection without a valid hello (%s)", self.robot_id, exc)
            return None
        if peer not in self.peers:
            self._count("bad_hello")
            log.warning("robot %s: robot %r connected but is not a --peer (%s)", self.robot_id, peer,
                        sorted(self.peers))
            return None
        return peer

    def _adopt(self, sock: socket.socket, expect: str | None) -> bool:
        peer = self._hello(sock)
        if peer is None or (expect is not None and peer != expect):
            if peer is not None:
                self._count("bad_hello")
                log.warning("robot %s: %s answered as robot %r, expected %r", self.robot_id,
                            self.peers.get(expect), peer, expect)
            sock.close()
            return False
        sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_KEEPALIVE, 1)
        sock.settimeout(self.conf["send_timeout_s"])
        conn = _Conn(self, peer, sock)
        with self._cond:
            old = self._conns.get(peer)
            self._conns[peer] = conn
        if old is not None:
            old.close("replaced by a new connection")
        conn.thread.start()
        self._count("connects")
        self._event("up", peer, "")
        log.info("robot %s: connected to robot %s", self.robot_id, peer)
        return True

    def _accept_loop(self) -> None:
        while not self._closing.is_set():
            try:
                sock, _ = self._server.accept()
            except socket.timeout:
                continue
            except OSError:
                break
            # hello in its own thread: a silent client must not block other accepts
            threading.Thread(target=self._adopt, args=(sock, None), daemon=True).start()

    def _dial_loop(self, peer: str, addr: Address) -> None:
        delay, failures = self.conf["backoff_initial_s"], 0
        while not self._closing.is_set():
            conn = self._conns.get(peer)
            if peer in self._finished or (conn is not None and not conn.closed.is_set()):
                self._closing.wait(0.2)
                delay = self.conf["backoff_initial_s"]
                continue
            try:
                sock = socket.create_connection((addr.host, addr.port), timeout=self.conf["dial_timeout_s"])
                if self._adopt(sock, peer):
                    failures = 0
                    continue
            except OSError as exc:
                failures += 1
                self._count("dial_failures")
                (log.info if failures == 1 else log.debug)(
                    "robot %s: robot %s at %s not reachable yet (%s); retrying", self.robot_id, peer, addr, exc)
            self._closing.wait(delay)
            delay = min(2 * delay, self.conf["backoff_max_s"])

    # ------------------------------------------------------------------ events
    def _count(self, what: str, n: int = 1) -> None:
        with self._cond:
            self.stats[what] += n

    def _event(self, what: str, peer: str, info: Any) -> None:
        with self._cond:
            if what == "garbled":
                self.stats["garbled"] += 1
            self._events.append((what, peer, info))
            self._cond.notify_all()

    def _on_frame(self, peer: str, frame: bytes) -> None:
        self._count("frames_received")
        try:
            msg = decode(frame)
        except MessageError as exc:
            self._event("garbled", peer, str(exc))
            return
        self._event("msg", peer, (msg, len(frame)))

    def _on_closed(self, conn: _Conn, why: str) -> None:
        with self._cond:
            current = self._conns.get(conn.peer) is conn
        if not current:
            return  # replaced: the new connection already said "up"
        if conn.said_bye:
            self._finished.add(conn.peer)
            self._event("bye", conn.peer, "")
        elif not (self._closing.is_set() or self._leaving.is_set()):
            self._count("peer_lost")
            log.warning("robot %s: lost robot %s (%s)", self.robot_id, conn.peer, why)
            self._event("down", conn.peer, why)

    def next_events(self, timeout_s: float) -> list[tuple]:
        """Events since the last call, waiting up to ``timeout_s`` for one.

        Each is ``(what, peer, info)``: ``msg`` (info = ``(Message, frame_bytes)``),
        ``garbled`` (info = reason), ``up``, ``down`` (info = reason), ``bye``.
        """
        with self._cond:
            if not self._events and timeout_s > 0:
                self._cond.wait(timeout_s)
            out, self._events = self._events, []
        return out

    # ------------------------------------------------------------------ sending
    def send(self, peer: str, frame: bytes) -> bool:
        """Send one message frame to ``peer``; False when it is not connected (nothing sent)."""
        conn = self._conns.get(peer)
        if conn is None or not conn.send(T_MSG, frame):
            return False
        kind = KIND_OF_TYPE.get(frame[3] if len(frame) > 3 else 0, "other")
        self._count(f"wire_bytes_{kind}", len(frame))
        self._count(f"frames_sent_{kind}")
        return True

    def broadcast(self, frame: bytes) -> list[str]:
        """Send to every connected peer; returns who it went to."""
        return [p for p in self.peers if self.send(p, frame)]

    def close(self, linger_s: float = 2.0) -> None:
        """Say bye, wait up to ``linger_s`` for the peers' byes (their last frames still arrive), close."""
        self._leaving.set()
        for conn in list(self._conns.values()):
            conn.send(T_BYE, b"")
        deadline = time.monotonic() + linger_s
        for conn in list(self._conns.values()):
            conn.closed.wait(max(0.0, deadline - time.monotonic()))
        self.abort()

    def abort(self) -> None:
        """Close everything at once, without byes (what a crash looks like to the peers)."""
        self._closing.set()
        for conn in list(self._conns.values()):
            conn.close("closing")
        try:
            self._server.close()
        except OSError:
            pass

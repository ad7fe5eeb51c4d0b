"""In-process message channel between robots of one team, optionally lossy.

Frames are the exact wire bytes of :mod:`cerpe.messages`. The channel counts what
each sender puts on the wire (per message kind) and can, with seeded
probabilities, drop a frame or garble it (flip bytes or truncate it) on its way
to each receiver. Receivers decode with :func:`cerpe.messages.decode`; a frame
that does not decode is counted as ``msg:garbled`` and skipped, a dropped frame
as ``msg:lost`` (the simulation knows what it dropped, a real receiver would see
a timeout).

A broadcast is one transmission on a shared medium: its bytes are counted once
for the sender, while loss and corruption are drawn per receiver.
"""
from __future__ import annotations

import logging
import zlib
from collections import Counter, defaultdict
from dataclasses import dataclass, field
from typing import Iterable

import numpy as np

from .errors import CerpeError
from .messages import Message, MessageError, decode

log = logging.getLogger(__name__)

KINDS: tuple[str, ...] = ("descriptor", "pose", "request", "reply", "estimate")


class TransportError(CerpeError, ValueError):
    """Misuse of the channel (unknown kind or robot, bad probabilities)."""


@dataclass
class Delivery:
    """What one receiver got since its last :meth:`Channel.receive`.

    Attributes:
        messages: decoded messages with the sending robot id, in send order.
        sizes: the wire size (bytes) of each of ``messages``.
        degradations: one ``"msg:lost"`` / ``"msg:garbled"`` entry per bad frame.
    """

    messages: list[tuple[str, Message]] = field(default_factory=list)
    sizes: list[int] = field(default_factory=list)
    degradations: list[str] = field(default_factory=list)


class Channel:
    """Synchronous in-process channel.

    Args:
        robots: ids of the robots attached to the channel.
        p_drop: probability that a frame never reaches a given receiver.
        p_garble: probability that a frame that is not dropped arrives corrupted.
        seed: seed of the loss/corruption draws (runs are reproducible).
    """

    def __init__(self, robots: Iterable[str] = (), p_drop: float = 0.0, p_garble: float = 0.0,
                 seed: int = 0) -> None:
        for name, p in (("p_drop", p_drop), ("p_garble", p_garble)):
            if not (np.isfinite(p) and 0.0 <= p <= 1.0):
                raise TransportError(f"channel: {name} must be a probability in [0, 1], got {p}")
        self.p_drop = float(p_drop)
        self.p_garble = float(p_garble)
        self._rng = np.random.default_rng(seed)
        self._inbox: dict[str, list[tuple[str, bytes | None]]] = {}
        self.bytes_sent: dict[str, Counter[str]] = defaultdict(Counter)
        self.frames_sent: dict[str, Counter[str]] = defaultdict(Counter)
        self.counts: Counter[str] = Counter()
        for r in robots:
            self.attach(r)

    @property
    def robots(self) -> list[str]:
        return list(self._inbox)

    def attach(self, robot: str) -> None:
        self._inbox.setdefault(str(robot), [])

    def _check(self, robot: str, role: str) -> None:
        if robot not in self._inbox:
            raise TransportError(f"channel: unknown {role} robot {robot!r} (attached: {self.robots})")

    def _garble(self, frame: bytes) -> bytes:
        buf = bytearray(frame)
        if len(buf) > 1 and self._rng.random() < 0.3:
            return bytes(buf[: int(self._rng.integers(0, len(buf)))])  # truncated
        for pos in self._rng.integers(0, len(buf), size=int(self._rng.integers(1, 4))):
            buf[pos] ^= int(self._rng.integers(1, 256))
        return bytes(buf)

    def _deliver(self, sender: str, frame: bytes, receiver: str) -> None:
        if self._rng.random() < self.p_drop:
            self._inbox[receiver].append((sender, None))
            return
        if self.p_garble > 0 and self._rng.random() < self.p_garble:
            frame = self._garble(frame)
        self._inbox[receiver].append((sender, frame))

    def _account(self, sender: str, kind: str, frame: bytes) -> int:
        self._check(sender, "sending")
        if kind not in KINDS:
            raise TransportError(f"channel: unknown message kind {kind!r}; expected one of {KINDS}")
        if not isinstance(frame, (bytes, bytearray)) or not frame:
            raise TransportError(f"channel: {sender} sent an empty or non-bytes {kind} frame")
        self.bytes_sent[sender][kind] += len(frame)
        self.frames_sent[sender][kind] += 1
        return len(frame)

    def send(self, sender: str, kind: str, frame: bytes, receiver: str) -> int:
        """Unicast ``frame`` to ``receiver``; returns the bytes counted for ``sender``."""
        n = self._account(sender, kind, frame)
        self._check(receiver, "receiving")
        self._deliver(sender, bytes(frame), receiver)
        return n

    def broadcast(self, sender: str, kind: str, frame: bytes) -> int:
        """Send ``frame`` to every other attached robot; bytes are counted once."""
        n = self._account(sender, kind, frame)
        for r in self._inbox:
            if r != sender:
                self._deliver(sender, bytes(frame), r)
        return n

    def receive(self, receiver: str) -> Delivery:
        """Drain ``receiver``'s inbox, decoding every frame."""
        self._check(receiver, "receiving")
        out = Delivery()
        pending, self._inbox[receiver] = self._inbox[receiver], []
        for sender, frame in pending:
            if frame is None:
                self.counts["msg:lost"] += 1
                out.degradations.append("msg:lost")
                continue
            try:
                out.messages.append((sender, decode(frame)))
                out.sizes.append(len(frame))
                self.counts["msg:delivered"] += 1
            except MessageError as exc:
                self.counts["msg:garbled"] += 1
                out.degradations.append("msg:garbled")
                log.debug("robot %s dropped a garbled frame from %s: %s", receiver, sender, exc)
        return out

    def total_bytes(self, sender: str | None = None) -> int:
        """All bytes sent (by ``sender``, or by everyone)."""
        senders = [sender] if sender is not None else list(self.bytes_sent)
        return int(sum(sum(self.bytes_sent[s].values()) for s in senders))


@dataclass(frozen=True)
class LossSpec:
    """The lossy channel of a run (``cerpe run --loss P --garble P --loss-seed N``).

    Each encounter gets its own :class:`Channel`, seeded from ``seed`` and the
    encounter's name (:meth:`channel`), so an encounter's draws depend on nothing
    run before it: the same seed reproduces a run (and a resumed one) bit for bit.
    """

    p_drop: float = 0.0
    p_garble: float = 0.0
    seed: int = 0

    def __post_init__(self) -> None:
        for name, p in (("loss", self.p_drop), ("garble", self.p_garble)):
            if not (np.isfinite(p) and 0.0 <= p <= 1.0):
                raise TransportError(f"--{name} {p}: must be a probability in [0, 1]")
        if int(self.seed) < 0:
            raise TransportError(f"--loss-seed {self.seed}: must be >= 0")

    @property
    def lossless(self) -> bool:
        return self.p_drop == 0.0 and self.p_garble == 0.0

    def as_dict(self) -> dict:
        """What run.json records (the seed only where something is drawn)."""
        return {"loss": self.p_drop, "garble": self.p_garble, "loss_seed": None if self.lossless else int(self.seed)}

    def channel(self, robots: Iterable[str], key: str) -> Channel:
        """A fresh channel for one encounter (``key``: its name)."""
        seq = np.random.SeedSequence([int(self.seed), zlib.crc32(str(key).encode())])
        return Channel(robots, self.p_drop, self.p_garble, seed=int(seq.generate_state(1)[0]))

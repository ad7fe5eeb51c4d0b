"""The in-process :class:`~cerpe.algorithm.link.Link`: a team's robots over one :class:`~cerpe.transport.Channel`.

Nothing waits: :class:`~cerpe.algorithm.team.Team` advances every engine to the
same wait point first, so a gather finds every frame of the phase already on the
channel (or counted lost by it). An image request is answered at once: the
requester's call delivers it to the owner, whose handler replies over the same
channel. Faults are those the channel draws (``msg:lost`` per dropped frame,
``msg:garbled`` per frame that does not decode), booked on the receiver.
"""
from __future__ import annotations

from typing import Mapping, Sequence

from ..transport import Channel
from .link import Inbox, Mailbox, RequestHandler


class ChannelHub:
    """The team's channel and each robot's mailbox; hands out one :class:`ChannelLink` per robot."""

    def __init__(self, channel: Channel, robot_ids: Sequence[str]) -> None:
        self.channel = channel
        self.robot_ids = [str(r) for r in robot_ids]
        self.mailboxes = {r: Mailbox(r, self.robot_ids) for r in self.robot_ids}
        for r in self.robot_ids:  # a fresh team starts with empty inboxes
            channel.attach(r)
            channel.receive(r)

    def link(self, robot_id: str) -> "ChannelLink":
        return ChannelLink(self, robot_id)

    def pump(self, robot_id: str) -> None:
        """Move ``robot_id``'s frames from the channel into its mailbox and answer its requests."""
        box = self.mailboxes[robot_id]
        d = self.channel.receive(robot_id)
        for what in d.degradations:
            box.degrade(what)
        replies = []
        for (sender, msg), nbytes in zip(d.messages, d.sizes):
            replies += box.file(sender, msg, nbytes)
        for peer, frame in replies + box.answer():
            self.channel.send(robot_id, "reply", frame, peer)


class ChannelLink:
    """One robot's end of a :class:`ChannelHub` (``deadline_s`` is never needed)."""

    def __init__(self, hub: ChannelHub, robot_id: str) -> None:
        self.hub, self.robot_id = hub, str(robot_id)
        self.box = hub.mailboxes[self.robot_id]

    def begin(self, step: int) -> None:
        self.box.begin(step)

    def broadcast(self, kind: str, frame: bytes) -> int:
        return self.hub.channel.broadcast(self.robot_id, kind, frame)

    def gather(self, step: int, kind: str, peers: Sequence[str], deadline_s: float) -> Inbox:
        self.hub.pump(self.robot_id)
        return self.box.inbox(step, kind, peers)

    def request(self, step: int, frames: Mapping[str, bytes], deadline_s: float) -> Inbox:
        sent = {}
        for peer, frame in frames.items():
            sent[peer] = self.hub.channel.send(self.robot_id, "request", frame, peer)
            self.hub.pump(peer)  # the owner answers now
        self.hub.pump(self.robot_id)
        inbox = self.box.inbox(step, "reply", list(frames))
        inbox.sent = sent
        return inbox

    def serve(self, handler: RequestHandler) -> None:
        self.box.handler = handler

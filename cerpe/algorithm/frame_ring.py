"""A robot's recent frames, held for the image requests of peers running at their own pace.

A peer asks for the frame its descriptor described, named by the frame's index and capture stamp,
while this robot may already be processing a later one. :class:`FrameRing` keeps the last ``keep``
frames and answers on the link's thread (a lock guards it), with the frame's odometry pose once this
robot has it (else its newest, as ``pose_step`` says). The JPEG (or WebP) of a frame is encoded
once. Reply bytes are counted here and handed to the robot's record by :meth:`take_bytes`.
"""
from __future__ import annotations

import dataclasses
import threading
from collections import OrderedDict

import numpy as np

from ..messages import ImageReply, ImageRequest
from ..scene import CameraIntrinsics
from .config import MessageConfig
from .frames import intrinsics_tuple

#: two stamps this close (s) name the same frame (a stamp travels as integer nanoseconds)
SAME_FRAME_S = 1e-6


@dataclasses.dataclass
class _Held:
    stamp_s: float
    image: np.ndarray
    intrinsics: CameraIntrinsics | None
    reply: ImageReply | None = None


class FrameRing:
    """The last ``keep`` frames of robot ``index``, by frame index; replies encoded with ``messages``'s codec."""

    def __init__(self, index: int, messages: MessageConfig, keep: int = 8) -> None:
        self.index, self.messages, self.keep = int(index), messages, int(keep)
        self._lock = threading.Lock()
        self._frames: OrderedDict[int, _Held] = OrderedDict()
        self._poses: OrderedDict[int, np.ndarray] = OrderedDict()
        self._bytes = 0
        self.n_replies = 0
        self.n_not_held = 0

    def hold(self, step: int, stamp_s: float, image: np.ndarray, intrinsics: CameraIntrinsics | None) -> None:
        with self._lock:
            self._frames[int(step)] = _Held(float(stamp_s), image, intrinsics)
            while len(self._frames) > self.keep:
                self._frames.popitem(last=False)

    def set_pose(self, step: int, T_odom_cam: np.ndarray) -> None:
        with self._lock:
            self._poses[int(step)] = np.array(T_odom_cam, dtype=np.float64)
            while len(self._poses) > self.keep:
                self._poses.popitem(last=False)

    def reply(self, peer: str, request: ImageRequest, stamp_s: float) -> bytes | None:
        """The reply frame to ``request`` for the frame of index ``request.step`` stamped ``stamp_s``;
        None when it is not held (gone from the ring, or another frame has that index)."""
        with self._lock:
            held = self._frames.get(int(request.step))
            if request.target != self.index or held is None or abs(held.stamp_s - float(stamp_s)) > SAME_FRAME_S:
                self.n_not_held += 1
                return None
            image, K, cached = held.image, held.intrinsics, held.reply
            pose_step = int(request.step) if int(request.step) in self._poses else \
                max((s for s in self._poses if s < request.step), default=-1)
            X = self._poses.get(pose_step)
        if cached is None:
            m = self.messages
            cached = ImageReply.from_image(self.index, int(request.step), image, intrinsics_tuple(K),
                                           quality=m.reply_quality, codec=m.reply_codec, scale=m.reply_scale)
            with self._lock:
                if int(request.step) in self._frames:
                    self._frames[int(request.step)].reply = cached
        frame = dataclasses.replace(cached, pose_step=pose_step if X is not None else -1, T_odom_cam=X).encode()
        with self._lock:
            self._bytes += len(frame)
            self.n_replies += 1
        return frame

    def take_bytes(self) -> int:
        """Reply bytes sent since the last call."""
        with self._lock:
            n, self._bytes = self._bytes, 0
            return n

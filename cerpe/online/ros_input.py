"""A robot's own ROS 2 topics as its frames (``cerpe online --input ros``), read over Zenoh without ROS.

Subscribes, on the link's Zenoh session, in either key layout (:mod:`cerpe.online.ros`), to:

* the camera: ``sensor_msgs/msg/Image`` (rgb8, bgr8, mono8, rgba8, bgra8) or ``CompressedImage``;
* its ``CameraInfo`` (intrinsics, ``plumb_bob`` / ``rational_polynomial`` distortion: images are
  undistorted as the ``rosbag`` adapter does);
* optionally an aligned depth ``Image`` (16UC1 mm, 32FC1 m), matched to an image within ``depth_tolerance_s``;
* optionally the robot's odometry: ``nav_msgs/msg/Odometry`` on ``odom_topic``, or TF ``odom_frame ->
  base_frame`` on ``/tf``; with the camera's extrinsic from ``/tf_static`` (base frame -> the image's
  frame id) or ``camera_extrinsic``. ``T_odom_cam = T_odom_base @ T_base_cam`` at the image's stamp.

Relative topic names resolve in ``namespace`` (default ``/<robot id>``). Messages are filed on
Zenoh's threads as they come (images kept raw, decoded only when taken); :meth:`RosInput.frames`
gives the newest image each time the robot is ready. Everything wrong with a message is counted
(:mod:`cerpe.reasons`, ``input:*``) on the next frame taken, with one warning per topic and kind of
fault; nothing raises. The run ends on :meth:`RosInput.stop` (Ctrl-C) or, with ``idle_exit_s``, when
no image came for that long.
"""
from __future__ import annotations

import logging
import threading
import time
from collections import Counter, deque
from typing import Any, Iterator, Mapping

import numpy as np

from ..config import merge_conf
from ..datasets.imageref import undistortion
from ..errors import CerpeError
from ..geometry import GeometryError, se3_from_tq_xyzw
from ..protocols import FrameContext
from ..rosio import decode
from ..rosio import types as rt
from ..rosio.tf import TfBuffer
from ..stamped_poses import StampedPoses
from . import ros
from .clock import StampClock
from .sources import Frame, StallWatch

log = logging.getLogger(__name__)

#: a sample's rmw_zenoh source time is taken as its arrival when it is at most this old (s): the publisher
#: runs on this machine (a camera driver, a bag player); older, its clock is another machine's
SOURCE_TIME_MAX_S = 5.0
#: an image taken waits at most this long (s) for its depth message and, the first time, its CameraInfo: a
#: driver publishes them beside the image, and they may come just after it
COMPANION_WAIT_S = 0.25

default_conf: dict[str, Any] = {
    "namespace": None,                # relative topics resolve here; None: /<robot id>
    "image_topic": "camera/image_raw",
    "camera_info_topic": None,        # None: camera_info beside the image topic
    "depth_topic": None,              # an aligned depth Image; None: no depth
    "odom_topic": None,               # nav_msgs/Odometry; None: none (or TF with tf_odometry)
    "tf_odometry": False,             # the robot's odometry from TF odom_frame -> base_frame
    "odom_frame": "odom",
    "base_frame": "base_link",
    "camera_extrinsic": None,         # T_base_cam as [x, y, z, qx, qy, qz, qw]; None: from /tf_static
    "key_format": "rmw_zenoh",        # how the topics reach Zenoh: rmw_zenoh | ros2dds
    "domain_id": 0,
    "depth_tolerance_s": 0.02,        # an image's depth: the nearest depth message within this (s)
    "odom_max_gap_s": 0.5,            # odometry interpolated between messages at most this far apart (s)
    "odom_max_extrapolation_s": 0.2,  # or extrapolated this far past the newest (s)
    "stall_s": 2.0,                   # a gap between images longer than this is counted (input:stall); 0: never
    "idle_exit_s": 0.0,               # end the run when no image came for this long (s); 0: never (Ctrl-C)
}


class RosInputConfError(CerpeError, ValueError):
    """A bad option of the ROS input (a topic name, an extrinsic, a tolerance)."""


def resolve(topic: str, namespace: str) -> str:
    """A ROS topic name: absolute as given, relative ones in ``namespace``."""
    topic = str(topic).strip()
    if not topic or any(c.isspace() for c in topic) or "//" in topic:
        raise RosInputConfError(f"topic {topic!r}: not a ROS topic name")
    return topic if topic.startswith("/") else f"{namespace.rstrip('/')}/{topic}"


def camera_info_beside(image_topic: str) -> str:
    """``camera_info`` beside the image topic (a ``.../compressed`` transport stepped over)."""
    parts = image_topic.rstrip("/").split("/")
    if parts[-1] in ("compressed", "compressedDepth") and len(parts) > 2:
        parts = parts[:-1]
    return "/".join(parts[:-1] + ["camera_info"])


def extrinsic(value: Any) -> np.ndarray | None:
    """``[x, y, z, qx, qy, qz, qw]`` (metres, scalar-last quaternion) as ``T_base_cam``."""
    if value is None:
        return None
    try:
        v = [float(x) for x in (value.replace(",", " ").split() if isinstance(value, str) else value)]
        if len(v) != 7:
            raise ValueError
        return se3_from_tq_xyzw(v[:3], v[3:])
    except (ValueError, TypeError, GeometryError):
        raise RosInputConfError(f"--camera-extrinsic {value!r}: expected 7 numbers 'x y z qx qy qz qw' "
                                f"(the camera's optical frame in the base frame, metres)") from None


class RosInput:
    """Robot ``robot_id``'s frames from its ROS 2 topics on ``session`` (see the module docstring)."""

    def __init__(self, session: Any, robot_id: str, conf: Mapping[str, Any] | None = None, seed: int = 0) -> None:
        self.conf = merge_conf(default_conf, conf, "ros input conf")
        c = self.conf
        if c["key_format"] not in ros.KEY_FORMATS:
            raise RosInputConfError(f"--input-keys {c['key_format']!r}: expected one of {ros.KEY_FORMATS}")
        for k in ("depth_tolerance_s", "odom_max_gap_s", "odom_max_extrapolation_s", "stall_s", "idle_exit_s"):
            if not float(c[k]) >= 0:
                raise RosInputConfError(f"ros input: {k} must be >= 0, got {c[k]!r}")
        if c["odom_topic"] and c["tf_odometry"]:
            raise RosInputConfError("--odom-topic and --tf-odometry: choose one source of the robot's odometry")
        ns = c["namespace"] if c["namespace"] is not None else f"/{robot_id}"
        self.robot_id, self.seed = robot_id, int(seed)
        self.topics = {"image": resolve(c["image_topic"], ns)}
        self.topics["camera_info"] = resolve(c["camera_info_topic"], ns) if c["camera_info_topic"] else \
            camera_info_beside(self.topics["image"])
        if c["depth_topic"]:
            self.topics["depth"] = resolve(c["depth_topic"], ns)
        if c["odom_topic"]:
            self.topics["odom"] = resolve(c["odom_topic"], ns)
        self.uses_odometry = bool(c["odom_topic"] or c["tf_odometry"])
        if self.uses_odometry:
            self.topics["tf"], self.topics["tf_static"] = "/tf", "/tf_static"
        self.T_base_cam = extrinsic(c["camera_extrinsic"])
        self.clock = StampClock()
        self.stalls = StallWatch(float(c["stall_s"]))
        self.stats: Counter[str] = Counter()
        self._cond = threading.Condition()
        self._stop = threading.Event()
        self._image: tuple[bytes, str, float] | None = None  # (payload, type, arrival) not taken yet
        self._depth: deque = deque(maxlen=30)  # (stamp, payload)
        self._camera: tuple[Any, tuple, Any] | None = None  # (intrinsics of the raw image, distortion, undistortion)
        self._odom = StampedPoses(keep=400)
        self._tf = TfBuffer(c["odom_frame"], c["base_frame"])
        self._pending: Counter[str] = Counter()  # degradations for the next frame taken
        self._warned: set[tuple[str, str]] = set()
        self._last_image_wall = time.time()
        self._last_stamp: float | None = None
        self._next_step = 0
        self._subs = [session.declare_subscriber(ros.subscription_key(topic, c), self._handler(role, topic))
                      for role, topic in self.topics.items()]

    # ------------------------------------------------------------------ filing (Zenoh threads)
    def _fault(self, what: str, topic: str, message: str) -> None:
        """Count ``what`` for the next frame, warn once per topic and fault (lock held)."""
        self._pending[what] += 1
        self.stats[what] += 1
        self._warn(what, topic, message)

    def _warn(self, what: str, topic: str, message: str) -> None:
        if (topic, what) not in self._warned:
            self._warned.add((topic, what))
            log.warning("robot %s: %s (%s; counted, further ones quietly)", self.robot_id, message, what)

    def _type_of(self, role: str, key: str, topic: str) -> str | None:
        """The message type of a sample on ``topic``: the rmw_zenoh key's, or the topic's for a bare key."""
        named = ros.key_type(key, self.conf)
        if named is not None:
            return named
        if role == "image":
            return rt.COMPRESSED_IMAGE if topic.rstrip("/").endswith("compressed") else rt.IMAGE
        return {"camera_info": rt.CAMERA_INFO, "depth": rt.IMAGE, "odom": rt.ODOMETRY, "tf": rt.TF_MESSAGE,
                "tf_static": rt.TF_MESSAGE}[role]

    def _handler(self, role: str, topic: str) -> Any:
        allowed = {"image": rt.IMAGE_TYPES, "camera_info": (rt.CAMERA_INFO,), "depth": (rt.IMAGE,),
                   "odom": (rt.ODOMETRY,), "tf": (rt.TF_MESSAGE,), "tf_static": (rt.TF_MESSAGE,)}[role]

        def on_sample(sample: Any) -> None:
            arrival = self._arrival(sample)
            payload = sample.payload.to_bytes()
            kind = self._type_of(role, str(sample.key_expr), topic)
            with self._cond:
                self.stats[f"received_{role}"] += 1
                if kind not in allowed:
                    self._fault("input:wrong-type", topic, f"{topic} carries {kind}; expected {' or '.join(allowed)}")
                    return
                try:
                    self._file(role, topic, kind, payload, arrival)
                except rt.RosInputError as exc:
                    what = {"camera_info": "input:bad-camera-info", "odom": "input:bad-odometry",
                            "tf": "input:bad-odometry", "tf_static": "input:bad-odometry"}.get(role, "input:wrong-type")
                    self._fault(what, topic, str(exc))
                self._cond.notify_all()

        return on_sample

    def _arrival(self, sample: Any) -> float:
        """When a sample came: rmw_zenoh's source time (the publisher's clock, on the robot: the driver's)
        when its attachment has one within the last seconds, else now. This process may run the callback
        late while it computes; the source time does not move with that."""
        now = time.time()
        if self.conf["key_format"] == "rmw_zenoh" and sample.attachment is not None:
            try:
                _, stamp_ns, _ = ros.parse_rmw_attachment(sample.attachment.to_bytes())
            except ros.RosError:
                return now
            if 0 <= now - stamp_ns * 1e-9 < SOURCE_TIME_MAX_S:
                return stamp_ns * 1e-9
        return now

    def _file(self, role: str, topic: str, kind: str, payload: bytes, arrival: float) -> None:
        if role == "image":
            if self._image is not None:
                self._pending["input:frame-dropped"] += 1
                self.stats["input:frame-dropped"] += 1
            self._image = (payload, kind, arrival)
            self._last_image_wall = time.time()
            return
        if role == "depth":
            self._depth.append((decode.stamp_s(rt.deserialize(payload, kind, topic)), payload))
            return
        msg = rt.deserialize(payload, kind, topic)
        if role == "camera_info":
            K, dist = decode.camera(msg, topic)
            if self._camera is None or self._camera[:2] != (K, dist):
                self._camera = (K, dist, undistortion(K, dist))
                log.info("robot %s: camera %dx%d fx %.1f fy %.1f from %s", self.robot_id, K.width, K.height,
                         K.fx, K.fy, topic)
        elif role == "odom":
            if not self._odom.add(decode.stamp_s(msg), decode.pose(msg, topic)):
                self.stats["odometry_not_kept"] += 1
        elif role == "tf":
            self._tf.add_dynamic(msg, topic)
        else:
            self._tf.add_static(msg, topic)

    # ------------------------------------------------------------------ taking (the robot's thread)
    def stop(self) -> None:
        self._stop.set()
        with self._cond:
            self._cond.notify_all()

    def frames(self) -> Iterator[Frame]:
        idle = float(self.conf["idle_exit_s"])
        while not self._stop.is_set():
            with self._cond:
                if self._image is None:
                    self._cond.wait(0.2)
                    if self._image is None:
                        if idle > 0 and time.time() - self._last_image_wall > idle and self.stats["taken"]:
                            log.info("robot %s: no image for %.1f s: input ended", self.robot_id, idle)
                            return
                        continue
                (payload, kind, arrival), self._image = self._image, None
                if self._camera is None:  # its CameraInfo may come just after the first image
                    self._cond.wait_for(lambda: self._camera is not None, COMPANION_WAIT_S)
                camera = self._camera
            frame = self._frame(payload, kind, arrival, camera)
            if frame is not None:
                self.stats["taken"] += 1
                yield frame

    def _take_pending(self, *more: str) -> tuple[str, ...]:
        with self._cond:
            out = [w for w, n in self._pending.items() for _ in range(n)]
            self._pending.clear()
        return tuple(out) + more

    def _count(self, what: str, topic: str, message: str) -> None:
        with self._cond:
            self._fault(what, topic, message)

    def _frame(self, payload: bytes, kind: str, arrival: float, camera: Any) -> Frame | None:
        topic = self.topics["image"]
        try:
            msg = rt.deserialize(payload, kind, topic)
        except rt.RosInputError as exc:  # a payload that is not the topic's type
            self._count("input:wrong-type", topic, str(exc))
            return None
        try:
            stamp = decode.stamp_s(msg)
            rgb = decode.image_rgb(msg, topic)
        except rt.RosInputError as exc:
            self._count("input:bad-image", topic, str(exc))
            return None
        if self._last_stamp is not None and stamp <= self._last_stamp:
            self._count("input:out-of-order", topic, f"{topic}: an image stamped {stamp:.6f} after one of "
                                                     f"{self._last_stamp:.6f}")
            return None
        if camera is None:
            self._count("input:no-camera-info", self.topics["camera_info"], f"an image before any usable "
                                                                            f"CameraInfo on {self.topics['camera_info']}")
            return None
        K, _, und = camera
        if rgb.shape[:2] != (K.height, K.width):
            self._count("input:bad-image", topic, f"{topic}: an image of {rgb.shape[1]}x{rgb.shape[0]} pixels, its "
                                                  f"CameraInfo says {K.width}x{K.height}")
            return None
        if und is not None:
            rgb = np.ascontiguousarray(und.apply(rgb, False, topic))
        self._last_stamp = stamp
        more = list(self.stalls.check(stamp))
        depth = self._match_depth(stamp, K, und, more) if "depth" in self.topics else None
        T = self._odometry(stamp, str(msg.header.frame_id)) if self.uses_odometry else None
        self.clock.note(stamp, arrival)
        t, self._next_step = self._next_step, self._next_step + 1
        ctx = FrameContext(self.robot_id, t, und.intrinsics if und is not None else K, depth, self.seed)
        return Frame(rgb, ctx, stamp, arrival, T, self._take_pending(*more))

    def _match_depth(self, stamp: float, K: Any, und: Any, degr: list[str]) -> np.ndarray | None:
        topic, tol = self.topics["depth"], float(self.conf["depth_tolerance_s"])
        with self._cond:  # its depth may come just after the image: until one at or after its stamp is here
            self._cond.wait_for(lambda: any(d[0] >= stamp - tol for d in self._depth), COMPANION_WAIT_S)
            near = min(self._depth, key=lambda d: abs(d[0] - stamp), default=None)
        if near is None or abs(near[0] - stamp) > tol:
            degr.append("input:no-depth")
            return None
        try:
            d = decode.depth_m(rt.deserialize(near[1], rt.IMAGE, topic), topic)
        except rt.RosInputError as exc:
            self._count("input:bad-depth", topic, str(exc))
            return None
        if d.shape != (K.height, K.width):
            self._count("input:bad-depth", topic, f"{topic}: depth of {d.shape[1]}x{d.shape[0]} pixels, the camera's "
                                                  f"{K.width}x{K.height} (publish depth aligned to the colour image)")
            return None
        return d if und is None else und.apply(d, True, topic)

    def _odometry(self, stamp: float, camera_frame: str) -> np.ndarray:
        """``T_odom_cam`` at ``stamp``; NaN (counted by the node) when not known."""
        c = self.conf
        with self._cond:
            poses = self._odom if c["odom_topic"] else self._tf.moving
            T_ob, _ = poses.at(stamp, float(c["odom_max_gap_s"]), float(c["odom_max_extrapolation_s"]))
            T_bc = self.T_base_cam if self.T_base_cam is not None else \
                self._tf.static_T(c["base_frame"], camera_frame)
        if T_ob is None or T_bc is None:  # the node counts input:no-odometry on this frame
            if T_bc is None:
                with self._cond:
                    self._warn("input:no-odometry", "/tf_static", f"no camera extrinsic: /tf_static does not "
                               f"connect {c['base_frame']} to the image's frame {camera_frame!r} (or give "
                               f"--camera-extrinsic)")
            return np.full((4, 4), np.nan)
        return T_ob @ T_bc

    def close(self) -> None:
        for sub in self._subs:
            sub.undeclare()
        self._subs = []

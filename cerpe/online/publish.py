"""A robot's estimates out: ROS 2 topics, optionally TF, and the newest one on a Zenoh queryable.

Per peer ``j`` with an estimate at a frame: a ``PoseWithCovarianceStamped`` on
``/cerpe/<team>/<i>/relative_pose/<j>`` (:mod:`cerpe.online.ros`), stamped at the frame's capture
time, with the estimate's covariance (the pose graph's, or the switch's propagation model's:
:mod:`cerpe.algorithm.switch_cov`). With ``tf``, one ``tf2_msgs/msg/TFMessage`` on ``/tf`` per frame:
each peer's camera ``<team>/<i>/peers/<j>/camera_optical`` as a child of this robot's camera
``<team>/<i>/camera_optical``, so RViz shows the peers around the robot. The newest estimate of each
peer is also served on the Zenoh queryable ``cerpe/<team>/<i>/latest/<j>`` (the same CDR bytes), for
a controller that polls between perception updates (``session.get("cerpe/lab/r0/latest/r1")``).
No liveliness tokens are declared, so ``ros2 topic list`` does not show the topics; name the type:
``ros2 topic echo /cerpe/lab/r0/relative_pose/r1 geometry_msgs/msg/PoseWithCovarianceStamped``.
"""
from __future__ import annotations

import os
import threading
import time
from typing import Any, Iterable, Mapping

import numpy as np

from ..config import merge_conf
from ..geometry import se3_inverse
from ..rosio import types as rt
from . import ros
from . import zenoh_wire as w
from .ros import RosError


class EstimatePublisher:
    """Publishes one robot's relative-pose estimates on a Zenoh session (e.g. ``ZenohLink.session``).

    Args:
        session: an open ``zenoh.Session``.
        team, robot_id: this robot's team and id (ROS name tokens).
        conf: overrides of :data:`cerpe.online.ros.default_conf`.
        tf: also publish the estimates as TF.
        latest: serve the newest estimate of each peer on a queryable.
    """

    def __init__(self, session: Any, team: str, robot_id: str, conf: Mapping[str, Any] | None = None,
                 tf: bool = False, latest: bool = True) -> None:
        self.conf = merge_conf(ros.default_conf, conf, "ros estimates conf")
        if self.conf["key_format"] not in ros.KEY_FORMATS:
            raise RosError(f"ros key_format {self.conf['key_format']!r}: expected one of {ros.KEY_FORMATS}")
        domain = self.conf["domain_id"]
        if not (isinstance(domain, int) and 0 <= domain <= 232):
            raise RosError(f"ros domain_id {domain!r}: expected an integer in 0..232 (ROS_DOMAIN_ID)")
        ros.check_distro(self.conf["distro"])
        self.session, self.team = session, ros.ros_token(team, "--team")
        self.robot_id = ros.ros_token(robot_id, "robot id")
        self.gid = os.urandom(16)
        self.tf = bool(tf)
        self._pubs: dict[str, Any] = {}
        self._seq: dict[str, int] = {}
        self._lock = threading.Lock()
        self._latest: dict[str, bytes] = {}
        self.n_published = 0
        self._queryable = (session.declare_queryable(w.latest_key(self.team, self.robot_id), self._on_query)
                           if latest else None)

    def key(self, other: str) -> str:
        return ros.zenoh_key(ros.topic_name(self.team, self.robot_id, other), self.conf)

    def _put(self, name: str, key: str, payload: bytes) -> None:
        if name not in self._pubs:
            self._pubs[name] = self.session.declare_publisher(key)
            self._seq[name] = 0
        self._seq[name] += 1
        if self.conf["key_format"] == "rmw_zenoh":
            self._pubs[name].put(payload, attachment=ros.rmw_attachment(self._seq[name], time.time_ns(), self.gid))
        else:
            self._pubs[name].put(payload)

    def publish(self, other: str, T_cj_ci: Any, stamp_s: float, covariance: Any = None) -> int:
        """Publish this robot's estimate ``T_cj_ci`` of ``other`` (``covariance``: 6x6 in ROS order, None:
        unknown); returns the CDR bytes."""
        cdr = ros.encode_pose_cdr(T_cj_ci, stamp_s, ros.camera_frame_id(self.team, other), covariance)
        self._put(other, self.key(other), cdr)
        with self._lock:
            self._latest[other] = cdr
        self.n_published += 1
        return len(cdr)

    def publish_pairs(self, pairs: Iterable[Any], covs: Mapping[str, np.ndarray | None] | None = None) -> int:
        """Publish every :class:`~cerpe.records.PairRecord` of this robot that has an estimate, with its
        covariance (``covs[other]``, else ``rec.cov``; right perturbation ``[rotation, translation]``), and
        with ``tf`` their TF; returns how many."""
        n, tfs = 0, []
        for rec in pairs:
            if rec.ego != self.robot_id or rec.T_cj_ci is None:
                continue
            cov = (covs or {}).get(rec.other, rec.cov)
            self.publish(rec.other, rec.T_cj_ci, rec.stamp_s, ros.ros_covariance(rec.T_cj_ci, cov) if cov is not None
                         else None)
            tfs.append((se3_inverse(rec.T_cj_ci), rec.stamp_s, ros.camera_frame_id(self.team, self.robot_id),
                        ros.peer_frame_id(self.team, self.robot_id, rec.other)))
            n += 1
        if self.tf and tfs:
            self._put("/tf", ros.zenoh_key("/tf", self.conf, rt.TF_MESSAGE), ros.encode_tf_cdr(tfs))
        return n

    def _on_query(self, query: Any) -> None:
        """Reply the newest estimate of each peer the query's key names (none yet: no reply)."""
        import zenoh

        with self._lock:
            latest = dict(self._latest)
        with query:
            for other, cdr in latest.items():
                key = w.latest_key(self.team, self.robot_id, other)
                if zenoh.KeyExpr(key).intersects(query.key_expr):
                    query.reply(key, cdr)

    def close(self) -> None:
        if self._queryable is not None:
            self._queryable.undeclare()
            self._queryable = None

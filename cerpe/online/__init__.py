"""CERPE online: one robot per process/machine, its team over Zenoh, its estimates out to ROS 2.

* :mod:`cerpe.online.zenoh_wire` -- where frames travel: key schema, link header (lock-step or
  by stamps).
* :mod:`cerpe.online.zenoh_session` -- opening a Zenoh session from cerpe's
  options (mode, endpoints, scouting) with one clear error.
* :mod:`cerpe.online.zenoh_link` -- :class:`ZenohLink`, the algorithm's link over Zenoh pub/sub,
  queryables and liveliness: by capture stamps (robots at their own pace, :mod:`~cerpe.online.zenoh_stream`)
  or in lock-step; its mixins :mod:`~cerpe.online.zenoh_receive` (filing the team's frames, counting),
  :mod:`~cerpe.online.zenoh_presence` (liveliness, byes, restarts, waiting for peers) and
  :mod:`~cerpe.online.zenoh_serve` (answering image queries).
* :mod:`cerpe.online.clock` -- a robot's capture-stamp clock and its peers' offsets.
* :mod:`cerpe.online.sources` -- frames from a manifest replay; :mod:`cerpe.online.ros_input` from
  the robot's ROS 2 topics.
* :mod:`cerpe.online.ros` -- ROS 2 keys (rmw_zenoh, zenoh-bridge-ros2dds) and the CDR of an estimate;
  :mod:`cerpe.online.publish` -- the estimates out (topics, TF, the newest on a queryable).
* :mod:`cerpe.online.node` -- :class:`RobotNode`, one robot's engine over a :class:`ZenohLink`.
* :mod:`cerpe.online.live` -- the run folder's encounter of a robot by stamps.
* :mod:`cerpe.online.run`, :mod:`cerpe.online.cli` -- ``cerpe online``; :mod:`cerpe.online.bag_play`,
  :mod:`cerpe.online.bag_cli` -- ``cerpe bag`` (play a bag's topics on Zenoh, write a dataset as bags).

``zenoh`` is imported when a link opens, ``rosbags`` when a ROS message is encoded or decoded.
"""
from .node import OnlineError, RobotNode
from .zenoh_link import ZenohLink, ZenohLinkError

__all__ = ["OnlineError", "RobotNode", "ZenohLink", "ZenohLinkError"]

"""CERPE online: one robot per process/machine, its team over Zenoh.

* :mod:`cerpe.online.zenoh_wire` -- where frames travel: key schema, link header.
* :mod:`cerpe.online.zenoh_session` -- opening a Zenoh session from cerpe's
  options (mode, endpoints, scouting) with one clear error.
* :mod:`cerpe.online.zenoh_link` -- :class:`ZenohLink`, the algorithm's link over
  Zenoh pub/sub, queryables and liveliness, loosely synchronised by step index
  with a deadline per wait; its mixins :mod:`~cerpe.online.zenoh_receive` (filing the
  team's frames, counting), :mod:`~cerpe.online.zenoh_presence` (liveliness, byes,
  waiting for peers) and :mod:`~cerpe.online.zenoh_serve` (answering image queries).
* :mod:`cerpe.online.ros` -- relative-pose estimates as ROS 2
  ``geometry_msgs/msg/PoseWithCovarianceStamped`` on rmw_zenoh / bridge keys.
* :mod:`cerpe.online.node` -- :class:`RobotNode`, one robot's step engine
  (the same phases as :class:`cerpe.algorithm.Team`) over a :class:`ZenohLink`.
* :mod:`cerpe.online.cli` -- ``cerpe online`` (replay one robot's frames of a
  manifest encounter, write its run folder).

``zenoh`` is imported when a link opens, ``rosbags`` when an estimate is encoded.
"""
from .node import OnlineError, RobotNode
from .zenoh_link import ZenohLink, ZenohLinkError

__all__ = ["OnlineError", "RobotNode", "ZenohLink", "ZenohLinkError"]

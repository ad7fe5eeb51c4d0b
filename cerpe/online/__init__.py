"""CERPE online: one robot per process/machine over a real network.

* :mod:`cerpe.online.net` -- TCP transport with length-prefixed frames, one
  connection per robot pair (why TCP only: see its docstring), redial with
  backoff, faults counted and never raised.
* :mod:`cerpe.online.tcp_link` -- :class:`TcpLink`, the algorithm's link over
  that transport, loosely synchronised by step index with a deadline per wait.
* :mod:`cerpe.online.node` -- :class:`RobotNode`, one robot's step engine
  (the same phases as :class:`cerpe.algorithm.Team`) over a :class:`TcpLink`.
* :mod:`cerpe.online.cli` -- ``cerpe online`` (replay one robot's frames of a
  manifest encounter, write its run folder).
"""
from .net import Address, NetTransport, OnlineError, parse_address, parse_peer
from .node import RobotNode
from .tcp_link import TcpLink

__all__ = ["Address", "NetTransport", "OnlineError", "RobotNode", "TcpLink", "parse_address", "parse_peer"]

"""CERPE online: one robot per process/machine over a real network.

* :mod:`cerpe.online.net` -- TCP transport with length-prefixed frames, one
  connection per robot pair (why TCP only: see its docstring), redial with
  backoff, faults counted and never raised.
* :mod:`cerpe.online.node` -- :class:`RobotNode`, the phases of
  :meth:`cerpe.algorithm.Team.step` from one robot's side, loosely synchronised
  by step index with a per-phase timeout.
* :mod:`cerpe.online.cli` -- ``cerpe online`` (replay one robot's frames of a
  manifest encounter, write its run folder).
"""
from .net import Address, NetTransport, OnlineError, parse_address, parse_peer
from .node import RobotNode

__all__ = ["Address", "NetTransport", "OnlineError", "RobotNode", "parse_address", "parse_peer"]

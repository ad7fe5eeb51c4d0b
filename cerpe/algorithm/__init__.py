"""CERPE, Algorithm 1 of the paper, for a team of robots exchanging real wire frames.

One step of one robot (:class:`StepEngine`, over a :class:`Link`):

1. describe its image (``encode``/``descriptor`` stages); a blank frame is found here;
2. broadcast a :class:`~cerpe.messages.DescriptorMessage`;
3. gate: cosine of the *wire* descriptors (both robots of a pair see the same
   score); ``score >= tau`` -> an :class:`~cerpe.messages.ImageRequest`, answered
   with a JPEG :class:`~cerpe.messages.ImageReply` (``gate`` stage);
4. ONE joint backbone pass over ``[current] + memory (newest first) (+ previous
   frame) + received images`` (``backbone``). With a :class:`Registrar` (``registrar``) the step's
   pass holds the own views only; the joint pass runs on a worker and its estimates land when
   ready, carried to the current frame with both odometries (``late``);
5. metric scale from the keyframes' depth references (``scale``);
6. odometry through the view the current one was measured against;
7. broadcast a :class:`~cerpe.messages.PoseMessage`;
8. per peer: a direct estimate when the gate opened and the collaborator was placed
   (through the joint pass or its registrations against single own views). It becomes
   the anchor when it is verified (:mod:`~cerpe.algorithm.anchors`); else the anchor is
   propagated with both odometries (``propagation``). With ``backend="graph"`` (not in
   the paper) the pair's robust pose graph over every direct estimate and both
   odometries replaces this (``graph``);
9. keyframe rule (:mod:`cerpe.memory`).

:class:`Team` runs N engines in one process over the lossy
:class:`~cerpe.transport.Channel`; ``cerpe.online`` runs one per process.
Run-time faults are counted under the names in :data:`DEGRADATIONS`; malformed
input raises :class:`AlgorithmError` naming robot, step and field.

Modules: ``config`` (parameters), ``frames`` (frame checks, blank test),
``poses`` (pose arithmetic), ``anchors`` (anchor verification), ``registrar`` and ``late``
(registration apart from the step), ``graph`` (the pose-graph
back end; ``graph_sim`` a simulated stream for it). ``policy`` decides when an open gate
requests the image, ``agent`` holds one robot's state and phases, ``link`` the link
protocol, ``engine`` the step; ``channel_link`` and ``team`` run a team in one process.
Online, robots at their own pace: ``stamp_engine`` (a step by capture stamps over a
``StreamLink``), ``frame_ring`` (recent frames for the peers' requests), ``switch_cov`` (the
switch's covariance from the pose graph's noise model).
The reasons and counted degradations are :mod:`cerpe.reasons`.
"""
from ..reasons import DEGRADATIONS
from .agent import RobotAgent
from .anchors import Anchor, AnchorConfig, PairAnchors
from .config import BACKENDS, PAPER_THRESHOLDS, AlgorithmConfig, AlgorithmError
from .engine import StepEngine, drive
from .graph import GRAPH_MODEL, DirectEstimate, GraphConfig, GraphEstimate, GraphModel, PairGraph
from .link import Inbox, Link, Mailbox, Received, StreamLink
from .policy import PairView, PolicyConfig
from .poses import direct_relative, ego_motion, registered_relative
from .registrar import Registrar, RegistrationJob, RegistrationResult, WorkerRegistrar
from .stamp_engine import StampEngine
from .team import Team, run_encounter

__all__ = ["BACKENDS", "DEGRADATIONS", "PAPER_THRESHOLDS", "AlgorithmConfig", "AlgorithmError", "Anchor", "AnchorConfig",
           "DirectEstimate", "GRAPH_MODEL", "GraphConfig", "GraphEstimate", "GraphModel", "Inbox", "Link", "Mailbox", "PairAnchors", "PairGraph", "PairView", "PolicyConfig",
           "Received", "Registrar", "RegistrationJob", "RegistrationResult", "RobotAgent", "StampEngine", "StepEngine", "StreamLink", "Team",
           "WorkerRegistrar", "direct_relative", "drive", "ego_motion",
           "registered_relative", "run_encounter"]

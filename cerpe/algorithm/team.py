"""A team of robots in one process: N step engines over the in-process lossy channel."""
from __future__ import annotations

from typing import Callable, Iterator, Sequence

import numpy as np

from ..protocols import DescriptorEncoder, FrameContext, MetricDepthSource, PoseBackbone
from ..records import StepResult
from ..scene import Encounter
from ..transport import Channel
from .agent import RobotAgent
from .channel_link import ChannelHub
from .config import AlgorithmConfig, AlgorithmError
from .engine import StepEngine, drive
from .registrar import Registrar


class Team:
    """N robots, one :class:`~cerpe.transport.Channel`, the three plug-ins, a config.

    Args:
        robot_ids: robot names in a fixed order (index = wire sender id).
        descriptor, backbone, depth: the plug-ins (:mod:`cerpe.protocols`), shared;
            they keep no per-robot state (what a backbone remembers about a view
            travels with the robot's kept frames as a memo).
        config: parameters; thresholds are resolved against the descriptor's
            calibration (see :class:`AlgorithmConfig`).
        channel: the medium; a lossless one by default.
        registrar: makes each robot's registrar from the backbone (received images registered apart
            from the step, landing when ready: :mod:`~cerpe.algorithm.late`); None: in the joint pass, every
            estimate at the step it was requested for (Algorithm 1, ``cerpe run``).
    """

    def __init__(self, robot_ids: Sequence[str], descriptor: DescriptorEncoder, backbone: PoseBackbone,
                 depth: MetricDepthSource, config: AlgorithmConfig | None = None,
                 channel: Channel | None = None,
                 registrar: Callable[[PoseBackbone], Registrar] | None = None) -> None:
        ids = [str(r) for r in robot_ids]
        if not ids or len(set(ids)) != len(ids) or len(ids) >= 2**16:
            raise AlgorithmError(f"team: robot ids must be unique and non-empty, got {ids}")
        self.robot_ids = ids
        self.descriptor, self.backbone, self.depth = descriptor, backbone, depth
        if callable(getattr(backbone, "serve_robots", None)):  # the robots share its caches
            backbone.serve_robots(len(ids))
        self.config = (config or AlgorithmConfig()).resolved(getattr(descriptor, "thresholds", None))
        self.channel = channel if channel is not None else Channel()
        self.make_registrar = registrar
        self.registrars: list[Registrar] = []
        self.reset()

    def reset(self) -> None:
        """Forget everything (memory, memos, odometry, anchors, frames in flight, registrations): a new
        encounter starts."""
        self.close()
        hub = ChannelHub(self.channel, self.robot_ids)
        make = self.make_registrar
        self.registrars = [make(self.backbone) for _ in self.robot_ids] if make is not None else []
        self.agents = [RobotAgent(r, i, self.config, self.descriptor, self.backbone, self.depth,
                                  self.registrars[i] if self.registrars else None)
                       for i, r in enumerate(self.robot_ids)]
        self.engines = [StepEngine(a, hub.link(a.robot_id), self.robot_ids) for a in self.agents]

    def close(self) -> None:
        """Stop the robots' registration workers (none without a registrar)."""
        for r in self.registrars:
            r.close()
        self.registrars = []

    def agent(self, robot_id: str) -> RobotAgent:
        for a in self.agents:
            if a.robot_id == robot_id:
                return a
        raise AlgorithmError(f"team: no robot {robot_id!r}")

    def step(self, images: Sequence[np.ndarray], contexts: Sequence[FrameContext],
             stamps_s: Sequence[float] | None = None) -> StepResult:
        """One synchronous round of Algorithm 1 for all robots, phase by phase (:class:`StepEngine`)."""
        n = len(self.engines)
        if len(images) != n or len(contexts) != n:
            raise AlgorithmError(f"team step: {len(images)} images and {len(contexts)} contexts for {n} robots")
        steps = {int(c.step) for c in contexts}
        if len(steps) != 1:
            raise AlgorithmError(f"team step: robots are at different steps {sorted(steps)}")
        done = drive([e.step(images[k], contexts[k], None if stamps_s is None else stamps_s[k])
                      for k, e in enumerate(self.engines)])
        return StepResult(step=steps.pop(), pairs=[p for r in done for p in r.pairs],
                          robots=[r.robots[0] for r in done])

    def run_encounter(self, encounter: Encounter, progress: bool = False, seed: int = 0,
                      max_steps: int | None = None) -> Iterator[StepResult]:
        """Reset and walk ``encounter`` step by step (images and sensor depth loaded lazily)."""
        if encounter.robot_ids != self.robot_ids:
            raise AlgorithmError(f"encounter {encounter.name}: robots {encounter.robot_ids} "
                                 f"differ from the team's {self.robot_ids}")
        self.reset()
        T = encounter.n_steps if max_steps is None else min(encounter.n_steps, int(max_steps))
        steps: Iterator[int] = iter(range(T))
        if progress:
            from tqdm.auto import tqdm

            steps = iter(tqdm(range(T), desc=f"cerpe {encounter.name}", unit="step"))
        for t in steps:
            images = [r.image(t) for r in encounter.robots]
            contexts = [FrameContext(r.robot_id, t, r.intrinsics, r.depth_m(t), seed) for r in encounter.robots]
            yield self.step(images, contexts, [float(r.stamps_s[t]) for r in encounter.robots])


def run_encounter(encounter: Encounter, descriptor: DescriptorEncoder, backbone: PoseBackbone,
                  depth: MetricDepthSource, config: AlgorithmConfig | None = None, channel: Channel | None = None,
                  progress: bool = False, seed: int = 0) -> Iterator[StepResult]:
    """Build a :class:`Team` for ``encounter``'s robots and walk it."""
    team = Team(encounter.robot_ids, descriptor, backbone, depth, config, channel)
    yield from team.run_encounter(encounter, progress=progress, seed=seed)

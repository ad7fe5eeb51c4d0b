"""The CERPE methods (``cerpe``, ``cerpe-wo-em``, ``cerpe-graph``) as a step source of run folders.

The configuration is the tree of :mod:`cerpe.method_config` (preset, the method's override,
dotted ``--set`` keys); :func:`cerpe_plugins_and_config` builds it with its plug-ins, the one
place ``cerpe run`` and ``cerpe online`` build a CERPE method from. :class:`CerpeSteps` runs
Algorithm 1 on an encounter. The three rows are views of ONE pass run with propagation and the
pose graph (:mod:`cerpe.pipeline.views`): :attr:`CerpeSteps.pass_key` names that pass, so that
:func:`cerpe.pipeline.run.run_methods` runs it once per encounter for the methods that share it.
"""
from __future__ import annotations

import dataclasses
import json
from typing import Any, Iterator, Mapping

from .. import knobs
from ..records import StepResult
from ..runfolder.layout import RunError
from ..runfolder.provenance import config_dict
from ..transport import LossSpec
from .views import switch_view, without_propagation


def cerpe_plugins_and_config(method: str, metric_depth: str | None, depth_options: dict | None = None,
                             preset: str = "paper", sets: Mapping[str, Any] | None = None) -> tuple[Any, Any, dict]:
    """Plug-ins, resolved :class:`~cerpe.method_config.CerpeConfig` and the run.json parameters of a CERPE method.

    One place for ``cerpe run`` and ``cerpe online``, so both build the same thing.
    """
    from .. import method_config
    from ..backbones.build import build_plugins

    try:
        tree = method_config.build(preset, method, sets)
    except method_config.ConfigError as exc:
        raise RunError(str(exc)) from None
    plugins = build_plugins(tree.backbone, depth=metric_depth, depth_options=depth_options)
    cfg = tree.resolved(getattr(plugins.descriptor, "thresholds", None))
    conf = {
        "tree": config_dict(knobs.as_dict(cfg)), "preset": preset, "sets": config_dict(dict(sets or {})),
        "depth": getattr(plugins.depth, "name", type(plugins.depth).__name__),
        "depth_options": config_dict(dict(depth_options or {})),
    }
    return plugins, cfg, conf


class CerpeSteps:
    """Algorithm 1 of one CERPE configuration: ``steps(encounter)`` yields its :class:`~cerpe.records.StepResult`.

    ``pass_key`` names the shared pass (``backend.kind = "graph"``, propagation on) whose :meth:`view`
    this configuration's records are, or is None for a configuration that reads the graph back
    (the "pays" request policy reads its sigma), which runs its own configuration. Two
    ``CerpeSteps`` with the same ``pass_key`` give the same :meth:`full_pass` of an encounter.
    """

    def __init__(self, plugins: Any, cfg: Any, conf: dict, seed: int, loss: LossSpec) -> None:
        self.plugins, self.cfg, self.seed, self.loss = plugins, cfg, int(seed), loss
        backend = cfg.backend
        self.pass_cfg = dataclasses.replace(cfg, backend=dataclasses.replace(backend, propagate=True, kind="graph"))
        shared = ((backend.propagate, backend.kind) in ((True, "switch"), (False, "switch"), (True, "graph"))
                  and cfg.policy.mode in ("gate", "always"))
        tree = conf["tree"]
        key = {**conf, "sets": None, "seed": self.seed,
               "tree": {**tree, "backend": {**tree["backend"], "propagate": None, "kind": None}}}
        self.pass_key: str | None = json.dumps(key, sort_keys=True, default=str) if shared else None

    def _run(self, encounter: Any, cfg: Any) -> Iterator[StepResult]:
        from .. import algorithm

        channel = None if self.loss.lossless else self.loss.channel(encounter.robot_ids, encounter.name)
        p = self.plugins
        return algorithm.run_encounter(encounter, p.descriptor, p.backbone, p.depth, config=cfg, channel=channel,
                                       seed=self.seed)

    def full_pass(self, encounter: Any) -> Iterator[StepResult]:
        """The shared pass of ``encounter`` (only for a ``pass_key``)."""
        if self.pass_key is None:
            raise ValueError("a configuration that is not a view of the shared pass has none")
        return self._run(encounter, self.pass_cfg)

    def view(self, res: StepResult) -> StepResult:
        """This configuration's records of one step of :meth:`full_pass`."""
        backend = self.cfg.backend
        if backend.kind == "graph":
            return res
        res = switch_view(res)
        return res if backend.propagate else without_propagation(res)

    def __call__(self, encounter: Any) -> Iterator[StepResult]:
        if self.pass_key is None:
            yield from self._run(encounter, self.cfg)
            return
        for res in self.full_pass(encounter):
            yield self.view(res)


def cerpe_steps(method: str, seed: int, metric_depth: str | None, depth_options: dict | None = None,
                loss: LossSpec = LossSpec(), preset: str = "paper",
                sets: Mapping[str, Any] | None = None) -> tuple[dict, CerpeSteps]:
    """``(run.json parameters, step source)`` of a CERPE method with the tree of ``preset``, ``method``, ``sets``."""
    plugins, cfg, conf = cerpe_plugins_and_config(method, metric_depth, depth_options, preset, sets)
    conf["channel"] = loss.as_dict()
    return conf, CerpeSteps(plugins, cfg, conf, seed, loss)

"""The "w/o EM" rows reuse the full method's pass; check that equals a real propagate=False run."""
from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from cerpe import algorithm
from cerpe.pipeline import run as run_mod
from cerpe.pipeline.views import without_propagation


@pytest.fixture(scope="module")
def fixture_encounter():
    from cerpe.synth import SUITES, render_encounter

    world, conf = SUITES["fixture"]["synthetic-cad"]
    return render_encounter(world, seed=2, conf=conf)  # direct at steps 0-1, propagated after


def test_derived_wo_em_equals_real_run(fixture_encounter):
    conf_full, steps_full = run_mod.prepare_method("cerpe", seed=0, metric_depth="mono-sim")
    full = list(steps_full(fixture_encounter))
    derived = [without_propagation(r) for r in full]

    from cerpe.backbones.build import build_plugins

    plugins = build_plugins(depth="mono-sim")
    cfg = algorithm.AlgorithmConfig().override({"backend.propagate": False}).resolved(plugins.descriptor.thresholds)
    real = list(algorithm.run_encounter(fixture_encounter, plugins.descriptor, plugins.backbone, plugins.depth,
                                        config=cfg, seed=0))
    assert len(real) == len(derived)
    n_prop = sum(p.source == "propagated" for r in full for p in r.pairs)
    assert n_prop > 0, "fixture too easy: nothing was propagated, the check would be empty"
    for a, b in zip(derived, real):
        for pa, pb in zip(a.pairs, b.pairs):
            assert (pa.ego, pa.other, pa.source, pa.gate_open, pa.reason) == (pb.ego, pb.other, pb.source, pb.gate_open, pb.reason)
            if pa.T_cj_ci is not None:
                np.testing.assert_allclose(pa.T_cj_ci, pb.T_cj_ci, atol=1e-9)
        for ra, rb in zip(a.robots, b.robots):
            np.testing.assert_allclose(ra.T_odom_cam, rb.T_odom_cam, atol=1e-9)


def _same_records(derived, real) -> None:
    assert len(derived) == len(real)
    for a, b in zip(derived, real):
        for pa, pb in zip(a.pairs, b.pairs):
            assert (pa.ego, pa.other, pa.source, pa.gate_open, pa.reason, pa.anchor_step, pa.bytes_pair,
                    pa.anchor_verdict) == (pb.ego, pb.other, pb.source, pb.gate_open, pb.reason, pb.anchor_step,
                                           pb.bytes_pair, pb.anchor_verdict)
            assert (pa.T_cj_ci is None) == (pb.T_cj_ci is None) and (pa.cov is None) == (pb.cov is None)
            if pa.T_cj_ci is not None:
                np.testing.assert_allclose(pa.T_cj_ci, pb.T_cj_ci, atol=1e-9)
            if pa.cov is not None:
                np.testing.assert_allclose(pa.cov, pb.cov, rtol=1e-9, atol=1e-15)
        for ra, rb in zip(a.robots, b.robots):
            assert ra.degradations == rb.degradations
            assert ra.bytes_sent == rb.bytes_sent
            np.testing.assert_allclose(ra.T_odom_cam, rb.T_odom_cam, atol=1e-9)


@pytest.mark.parametrize("method,backend,propagate", [("cerpe", "switch", True), ("cerpe-graph", "graph", True),
                                                      ("cerpe-wo-em", "switch", False)])
def test_each_cerpe_row_is_a_view_of_one_pass(fixture_encounter, method, backend, propagate):
    """cerpe, cerpe-graph and cerpe-wo-em share ONE pass (backend='graph', propagation on);
    each view equals a real run of its own configuration, field by field."""
    from cerpe.backbones.build import build_plugins

    _, steps = run_mod.prepare_method(method, seed=0, metric_depth="mono-sim")
    derived = list(steps(fixture_encounter))
    plugins = build_plugins(depth="mono-sim")
    cfg = algorithm.AlgorithmConfig().override({"backend.propagate": propagate, "backend.kind": backend}).resolved(plugins.descriptor.thresholds)
    real = list(algorithm.run_encounter(fixture_encounter, plugins.descriptor, plugins.backbone, plugins.depth,
                                        config=cfg, seed=0))
    _same_records(derived, real)
    if backend == "switch":
        assert all(p.switch is None and p.cov is None for r in derived for p in r.pairs)
        assert all(r.timings_s["graph"] == 0.0 for r in derived for r in r.robots)
    else:
        assert any(p.cov is not None for r in derived for p in r.pairs)

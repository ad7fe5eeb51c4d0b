"""The "w/o EM" rows reuse the full method's pass; check that equals a real propagate=False run."""
from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from cerpe import algorithm
from cerpe.pipeline import run as run_mod


@pytest.fixture(scope="module")
def fixture_encounter():
    from cerpe.synth import SUITES, render_encounter

    world, conf = SUITES["fixture"]["synthetic-cad"]
    return render_encounter(world, seed=2, conf=conf)  # direct at steps 0-1, propagated after


def test_derived_wo_em_equals_real_run(fixture_encounter):
    conf_full, steps_full = run_mod.prepare_method("cerpe", "offline", seed=0, metric_depth="mono-sim")
    full = list(steps_full(fixture_encounter))
    derived = [run_mod.without_propagation(r) for r in full]

    from cerpe.backbones.build import build_plugins

    plugins = build_plugins("offline", depth="mono-sim")
    cfg = dataclasses.replace(algorithm.CerpeConfig(), propagate=False).resolved(plugins.descriptor.thresholds)
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

"""The Pareto step on a tiny fake setting: runs per preset on a subset of encounters, cached; the
table's ratios; the figure; the presets and --set knobs of a real cerpe run."""
from __future__ import annotations

import pytest

from cerpe import plotting
from cerpe.method_config import PRESETS
from cerpe.pipeline import pareto
from cerpe.pipeline import run as rp

from test_pipeline_run_eval import _fake_steps, _setting

REPLY = {"always": 1000, "gate": 500, "pays": 100}
SCHEMES = ("always", "pays")


@pytest.fixture()
def fake(monkeypatch):
    calls = []

    def prepare(method, seed, depth=None, every=1, depth_options=None, channel=None, preset="paper", sets=None):
        mode = PRESETS[preset].get("policy.mode", "gate")
        calls.append(mode)

        def steps(enc):
            for res in _fake_steps(noise_rad={"always": 0.05, "gate": 0.1, "pays": 0.11}[mode])(enc):
                for r in res.robots:
                    r.bytes_sent = {"descriptor": 100, "reply": REPLY[mode]}
                for p in res.pairs:
                    p.bytes_pair, p.request_skipped = REPLY[mode], mode == "pays"
                yield res
        return {"fake": True, "mode": mode}, steps

    monkeypatch.setattr(rp, "prepare_method", prepare)
    return calls


def test_pareto_runs_only_the_named_encounters(tmp_path, fake):
    m = tmp_path / "toy.yaml"
    m.write_text("name: toy\n")
    s = _setting(n_steps=4, n_enc=3)
    runs, errors = pareto.scheme_runs([("toy", m, s)], tmp_path / "runs", schemes=("pays",),
                                      n_encounters=None, progress=False, only=["enc[02]"])
    assert not errors and sorted(p.name for p in runs[0].path.iterdir() if p.is_dir()) == ["enc0", "enc2"]
    none, errors = pareto.scheme_runs([("toy", m, s)], tmp_path / "runs", schemes=("pays",),
                                      progress=False, only=["other-*"])
    assert none == [] and errors == []


def test_pareto_runs_a_subset_once_and_tabulates_bytes_against_errors(tmp_path, fake):
    m = tmp_path / "toy.yaml"
    m.write_text("name: toy\n")
    s = _setting(n_steps=6, n_enc=3)
    runs, errors = pareto.scheme_runs([("toy", m, s)], tmp_path / "runs", schemes=SCHEMES, n_encounters=1,
                                      progress=False)
    assert not errors and [r.scheme for r in runs] == ["always", "pays"] and fake == ["always", "pays"]
    assert sorted(p.name for p in runs[0].path.iterdir() if p.is_dir()) == ["enc0"]  # the subset only
    # cached: found again without running; located without building; a changed setting runs anew
    again, _ = pareto.scheme_runs([("toy", m, s)], tmp_path / "runs", schemes=SCHEMES, n_encounters=1)
    assert again == runs and len(fake) == 2
    found, errs = pareto.scheme_runs([("toy", m, None)], tmp_path / "runs", schemes=SCHEMES, build=False)
    assert found == runs and not errs
    missing, errs = pareto.scheme_runs([("toy", m, None)], tmp_path / "runs", build=False, schemes=("pays",),
                                       knob_sets={"policy.max_steps": 3})
    assert not missing and "no current run" in errs[0]
    # the paper protocol: a full run of all encounters, read on the subset's encounters only
    paper = rp.run_method(m, "cerpe", tmp_path / "runs" / "toy" / "cerpe", setting=s, progress=False)
    runs.append(pareto.SchemeRun("toy", "paper", paper, ("enc0",)))
    t = pareto.pareto_table(runs)
    assert set(t["setting"]) == {"toy", "all"}
    row = t[(t["setting"] == "all")].set_index("scheme")
    assert row.loc["always", "bytes_per_robot_step"] == pytest.approx(1100)
    assert row.loc["pays", "vs_always"] == pytest.approx(200 / 1100)
    assert row.loc["pays", "image_vs_paper"] == pytest.approx(100 / 500)
    assert row.loc["paper", "e_rot_rad"] == pytest.approx(0.1, abs=1e-6)
    assert row.loc["always", "e_rot_rad"] == pytest.approx(0.05, abs=1e-6)
    assert row.loc["paper", "n_frames"] == row.loc["pays", "n_frames"] == 2 * 6  # one encounter each
    assert row.loc["pays", "requests_skipped"] == 2 * 6 and row.loc["paper", "requests_skipped"] == 0
    c = pareto.check(t, "pays")
    assert c["bytes_vs_always"] == pytest.approx(200 / 1100) and c["e_rot_vs_paper"] == pytest.approx(1.1, abs=1e-4)
    assert c["success_vs_paper"] == pytest.approx(1.0)
    parts = pareto.breakdown(runs).set_index("scheme")
    assert parts.loc["pays", "descriptor"] == 100 and parts.loc["pays", "reply"] == REPLY["pays"]
    assert parts.loc["pays", "pose"] == 0 and parts.loc["pays", "requests"] == 2 * 6  # every pair row has bytes
    assert parts.loc["pays", "placed"] == pytest.approx(4 / 6)  # the fake places nothing before step 2
    assert parts.loc["pays", "n_direct"] == 2 * 4 and parts.loc["pays", "n_propagated"] == 0
    assert parts.loc["pays", "e_rot_direct_rad"] == pytest.approx(0.11, abs=1e-6)
    md = pareto.format_markdown(t)
    assert md.count("\n") == 2 + 3 and "ours: request when it pays" in md
    out = plotting.save_figure(plotting.pareto_figure(t), tmp_path / "fig" / "pareto")
    assert all(p.stat().st_size > 1000 for p in out)
    with pytest.raises(pareto.ParetoError):
        pareto.check(t, "pays-int8")


def test_presets_and_sets_reach_the_cerpe_config_strictly():
    conf, _ = rp.prepare_method("cerpe", 0, "mono-sim", preset="pays",
                                sets={"policy.max_steps": 7, "messages.reply_quality": 60})
    tree = conf["tree"]
    assert tree["policy"]["mode"] == "pays" and tree["policy"]["max_steps"] == 7
    assert tree["messages"]["reply_quality"] == 60 and tree["policy"]["max_sigma_pos_m"] == 0.3
    assert conf["preset"] == "pays" and conf["sets"] == {"policy.max_steps": 7, "messages.reply_quality": 60}
    with pytest.raises(rp.RunError, match="unknown key 'policy.modus'; known under policy: mode"):
        rp.prepare_method("cerpe", 0, "mono-sim", sets={"policy.modus": "pays"})
    with pytest.raises(rp.RunError, match="unknown preset 'nope'; known: paper, graph"):
        rp.prepare_method("cerpe", 0, "mono-sim", preset="nope")
    with pytest.raises(rp.RunError, match="messages.reply_quality: expected int"):
        rp.prepare_method("cerpe", 0, "mono-sim", sets={"messages.reply_quality": "abc"})
    with pytest.raises(rp.RunError, match="cerpe methods only"):
        rp.prepare_method("sift-ransac", 0, sets={"messages.reply_quality": 60})
    # the method's own override comes after the preset
    conf, _ = rp.prepare_method("cerpe-wo-em", 0, "mono-sim", preset="graph")
    assert conf["tree"]["backend"] == {"kind": "graph", "propagate": False,
                                       "graph": {"window_nodes": 20, "kernel_k": 2.0}}


@pytest.mark.parametrize("name", pareto.PARETO_PRESETS)
def test_every_pareto_preset_builds_and_round_trips(name):
    from cerpe import knobs
    from cerpe.method_config import CerpeConfig, build

    conf, _ = rp.prepare_method("cerpe", 0, "mono-sim", preset=name)
    tree = build(name)
    assert knobs.from_dict(CerpeConfig, knobs.as_dict(tree)) == tree  # run.json's record rebuilds the same tree
    for key, value in PRESETS[name].items():
        group, leaf = key.split(".")
        assert conf["tree"][group][leaf] == value, key


def test_lean_preset_backs_off_and_rechecks_over_the_compressed_messages():
    from cerpe.method_config import build

    cfg = build("lean")
    pol = cfg.policy
    assert pol.mode == "pays" and pol.miss_limit == 3 and pol.miss_backoff_steps == 3
    assert pol.unanchored_backoff_steps == 2 and pol.backoff_pending_exempt
    assert pol.recheck_rot_rad == 0.03 and pol.recheck_limit == 1
    msgs = cfg.messages
    assert (msgs.descriptor_codec, msgs.reply_codec, msgs.reply_quality, msgs.reply_scale) == \
        ("pca-int8", "webp-grey", 75, 1.0)

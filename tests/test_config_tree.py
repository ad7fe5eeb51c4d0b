"""The configuration tree: every knob documented, docs/config.md generated from it, presets, strict errors."""
from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

from cerpe import config_show, knobs, method_config
from cerpe.method_config import PRESETS, CerpeConfig, ConfigError, build

ROOT = Path(__file__).resolve().parents[1]
MAX_KNOBS = 120


def test_every_knob_and_group_has_a_one_line_description():
    tree = CerpeConfig()
    missing = [k.path for k in knobs.knobs(tree) if not k.doc.strip() or "\n" in k.doc]
    assert not missing, f"knobs without a one-line description: {missing}"
    assert all(doc.strip() for _, doc in knobs.groups(tree))
    assert knobs.count(tree) <= MAX_KNOBS
    with pytest.raises(knobs.KnobError, match="description"):
        knobs.knob(1, "  ")


def test_docs_config_md_is_generated_from_the_tree():
    text = (ROOT / "docs" / "config.md").read_text()
    assert text == config_show.render_markdown(), (
        "docs/config.md is stale: regenerate it with `cerpe config show --markdown > docs/config.md`")
    for k in knobs.knobs(CerpeConfig()):
        assert f"`{k.path}`" in text


@pytest.mark.parametrize("name", list(PRESETS))
def test_every_preset_builds_and_sets_only_known_knobs(name):
    tree = build(name)
    paths = {k.path: k.value for k in knobs.knobs(tree)}
    for key, value in PRESETS[name].items():
        assert paths[key] == value, key
    assert name in method_config.PRESET_NOTES
    # the text the command prints reads back as the same tree (YAML values)
    import yaml

    flat = knobs.flatten(yaml.safe_load(config_show.render_tree(tree, "t")))
    assert build("paper", "cerpe", flat) == tree


def test_method_overrides_come_after_the_preset_and_sets_after_both():
    assert build("graph", "cerpe-wo-em").backend.kind == "graph"
    assert build("paper", "cerpe-wo-em").backend.propagate is False
    assert build("paper", "cerpe-graph", {"backend.kind": "switch"}).backend.kind == "switch"
    # dotted keys and nested dicts are the same thing
    assert build(sets={"policy.mode": "pays"}) == build(sets={"policy": {"mode": "pays"}}) == build("pays")


@pytest.mark.parametrize("sets, message", [
    ({"anchors.rot_tol": 0.1}, "unknown key 'anchors.rot_tol'; known under anchors: verify, rot_tol_rad"),
    ({"delta_k": 2}, "unknown key 'delta_k'; known: gate, memory"),
    ({"memory.delta_k": "abc"}, r"memory.delta_k: expected int, got 'abc'"),
    ({"messages.reply_quality": float("nan")}, "messages.reply_quality: expected int"),
    ({"gate.tau": 2.0}, r"gate.tau: must be <= 1.0"),
    ({"policy.mode": "sometimes"}, r"policy.mode: 'sometimes' is not one of \['gate', 'pays', 'always'\]"),
    ({"backend": 3}, "backend: a group of knobs"),
    ({"backbone.offline.cross.matcher": "sift"}, "backbone.offline.cross.matcher"),
])
def test_a_bad_key_or_value_is_one_error_naming_it(sets, message):
    with pytest.raises(ConfigError, match=message):
        build(sets=sets)


def test_unknown_preset_and_method_list_the_known_ones():
    with pytest.raises(ConfigError, match="unknown preset 'fast'; known: paper, graph, always, pays"):
        build("fast")
    with pytest.raises(ConfigError, match="cerpe methods: cerpe, cerpe-wo-em, cerpe-graph"):
        build(method="sift-ransac")


def test_parse_sets_reads_yaml_values_and_refuses_a_bad_item():
    assert method_config.parse_sets(["a.b=0.3", "c=true", "d=paper", "a.b=1"]) == {"a.b": 1, "c": True,
                                                                                  "d": "paper"}
    for bad in ("novalue", "=1", "a..b=1", "a=[1"):
        with pytest.raises(ConfigError, match="--set"):
            method_config.parse_sets([bad])


def _cli(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "cerpe.cli", *args], capture_output=True, text=True, timeout=120)


def test_config_show_command():
    out = _cli("config", "show", "--preset", "lean")
    assert out.returncode == 0, out.stderr
    assert "mode: pays  #" in out.stdout and "[default: gate]" in out.stdout
    assert "tau: null" in out.stdout and "resolves to" in out.stdout
    count = _cli("config", "show", "--count")
    assert count.returncode == 0 and int(count.stdout) == knobs.count(CerpeConfig())
    for args, message in ((("--preset", "nope"), "unknown preset 'nope'; known: paper"),
                          (("--set", "memory.delta_k=abc"), "memory.delta_k: expected int"),
                          (("--set", "anchors.nope=1"), "known under anchors: verify")):
        bad = _cli("config", "show", *args)
        assert bad.returncode == 2 and "Traceback" not in bad.stderr
        assert len(bad.stderr.strip().splitlines()) == 1 and message in bad.stderr, bad.stderr

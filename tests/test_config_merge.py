"""The one strict configuration merge (cerpe.config.merge_conf)."""
import pytest

from cerpe.config import ConfigError, merge_conf

DEFAULT = {"a": 1, "dense": {"stride": 8, "iterations": 6, "levels": 3}, "xfeat": {}, "opt": None}


def test_nested_merge_keeps_other_defaults():
    out = merge_conf(DEFAULT, {"dense": {"stride": 4}})
    assert out["dense"] == {"stride": 4, "iterations": 6, "levels": 3}
    assert out["a"] == 1


def test_defaults_are_not_mutated():
    out = merge_conf(DEFAULT, {"dense": {"stride": 4}})
    out["dense"]["levels"] = 99
    assert DEFAULT["dense"] == {"stride": 8, "iterations": 6, "levels": 3}


def test_unknown_key_lists_known_ones():
    with pytest.raises(ConfigError, match=r"unknown option\(s\) 'strid'.*known: iterations, levels, stride"):
        merge_conf(DEFAULT, {"dense": {"strid": 4}}, "offline")
    with pytest.raises(ConfigError, match=r"offline: unknown option\(s\) 'b'"):
        merge_conf(DEFAULT, {"b": 2}, "offline")


def test_open_and_none_defaults_take_anything():
    out = merge_conf(DEFAULT, {"xfeat": {"top_k": 512}, "opt": {"x": 1}})
    assert out["xfeat"] == {"top_k": 512} and out["opt"] == {"x": 1}


def test_type_mismatch_is_an_error():
    with pytest.raises(ConfigError, match="dense: expected a mapping"):
        merge_conf(DEFAULT, {"dense": 3})
    with pytest.raises(ConfigError, match="a: expected a single value"):
        merge_conf(DEFAULT, {"a": {"x": 1}})
    with pytest.raises(ConfigError, match="expected a mapping of options"):
        merge_conf(DEFAULT, [1, 2])  # type: ignore[arg-type]


def test_none_override_is_the_defaults():
    assert merge_conf(DEFAULT, None) == DEFAULT

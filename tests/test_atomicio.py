"""Atomic writes and checked reads (:mod:`cerpe.atomicio`): round trips, and every failure an
:class:`AtomicIOError` naming the file, with no temporary file left behind."""
from __future__ import annotations

import json

import numpy as np
import pytest

from cerpe.atomicio import (
    AtomicIOError, atomic_write_bytes, atomic_write_json, atomic_write_npz, atomic_write_text, read_json,
)


def _leftovers(folder):
    return sorted(p.name for p in folder.iterdir() if p.name.endswith(".tmp"))


def test_bytes_text_json_round_trip_and_overwrite(tmp_path):
    atomic_write_bytes(tmp_path / "a.bin", b"\x00\x01")
    assert (tmp_path / "a.bin").read_bytes() == b"\x00\x01"
    atomic_write_text(tmp_path / "a.bin", "replaced")
    assert (tmp_path / "a.bin").read_text() == "replaced"
    atomic_write_json(tmp_path / "sub" / "r.json", {"x": np.float32(0.5), "n": np.int64(3), "v": np.arange(2)})
    assert read_json(tmp_path / "sub" / "r.json", "result") == {"x": 0.5, "n": 3, "v": [0, 1]}
    assert _leftovers(tmp_path) == [] and _leftovers(tmp_path / "sub") == []


def test_npz_round_trip_keeps_the_name_as_given(tmp_path):
    rng = np.random.default_rng(0)
    a = rng.normal(size=(4, 3)).astype(np.float32)
    dst = tmp_path / "centres.npz"
    atomic_write_npz(dst, centres=a, source=np.array("test"), n=np.array(7))
    with np.load(dst) as z:
        assert sorted(z.files) == ["centres", "n", "source"]
        np.testing.assert_array_equal(z["centres"], a)
        assert str(z["source"]) == "test" and int(z["n"]) == 7
    odd = tmp_path / "cache.bin"  # no .npz appended, unlike np.savez on a path
    atomic_write_npz(odd, x=np.zeros(2))
    assert odd.is_file() and not (tmp_path / "cache.bin.npz").exists()
    assert _leftovers(tmp_path) == []


@pytest.mark.parametrize("writer", [
    lambda p: atomic_write_bytes(p, b"x"),
    lambda p: atomic_write_json(p, {"a": 1}),
    lambda p: atomic_write_npz(p, a=np.zeros(3)),
])
def test_a_folder_or_a_file_in_the_way_is_a_named_error(tmp_path, writer):
    (tmp_path / "taken").mkdir()
    with pytest.raises(AtomicIOError, match="taken"):
        writer(tmp_path / "taken")  # a folder where the file belongs
    (tmp_path / "plain").write_text("a file")
    with pytest.raises(AtomicIOError, match="plain is a file, not a folder"):
        writer(tmp_path / "plain" / "out.dat")  # a file where a folder belongs
    assert _leftovers(tmp_path) == []


def test_read_json_names_the_file_and_what_is_wrong(tmp_path):
    with pytest.raises(AtomicIOError, match=r"run folder: file not found: .*run\.json"):
        read_json(tmp_path / "run.json", "run folder")
    (tmp_path / "half.json").write_text('{"a": [1, 2')
    with pytest.raises(AtomicIOError, match=r"corrupt or half-written JSON in .*half\.json"):
        read_json(tmp_path / "half.json", "run folder")
    (tmp_path / "list.json").write_text(json.dumps([1, 2]))
    with pytest.raises(AtomicIOError, match=r"expected a JSON object in .*list\.json"):
        read_json(tmp_path / "list.json", "run folder")
    with pytest.raises(AtomicIOError, match="is a folder, not a file"):
        read_json(tmp_path, "run folder")

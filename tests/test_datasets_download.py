"""`cerpe data download` against a local HTTP server on 127.0.0.1 (never the internet).

The server serves archives the tests build (a tiny TUM RGB-D sequence as .tgz, a
7-Scenes-style scene zip holding per-sequence zips), honours Range requests, and
can drop the connection half-way through a response.
"""
from __future__ import annotations

import hashlib
import io
import tarfile
import threading
import zipfile
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from pathlib import Path

import pytest
import yaml

from cerpe import cli
from cerpe.datasets import load_setting
from cerpe.datasets.data_cli import lookup, manifest_lines
from cerpe.datasets.download import MARKER, DownloadError, extract, fetch, finished
from test_datasets_sequences import write_frames, write_tum

TUM_NAME = "rgbd_dataset_freiburg1_xyz"


class Server:
    """A small file server: ``files`` by path; ``drop_first`` bytes then hang up on the first GET; Range support."""

    def __init__(self, files: dict[str, bytes], drop_first: int | None = None, ranges: bool = True) -> None:
        self.files, self.drop_first, self.ranges = files, drop_first, ranges
        self.requests: list[tuple[str, str | None]] = []
        srv = self

        class Handler(BaseHTTPRequestHandler):
            def log_message(self, *args) -> None:  # quiet
                pass

            def do_GET(self) -> None:
                rng = self.headers.get("Range")
                srv.requests.append((self.path, rng))
                data = srv.files.get(self.path)
                if data is None:
                    self.send_error(404, "no such file")
                    return
                start = int(rng.split("=")[1].split("-")[0]) if rng and srv.ranges else 0
                if start >= len(data) and rng and srv.ranges:
                    self.send_response(416)
                    self.send_header("Content-Range", f"bytes */{len(data)}")
                    self.end_headers()
                    return
                body = data[start:]
                self.send_response(206 if start or (rng and srv.ranges) else 200)
                if rng and srv.ranges:
                    self.send_header("Content-Range", f"bytes {start}-{len(data) - 1}/{len(data)}")
                self.send_header("Content-Length", str(len(body)))
                self.end_headers()
                if srv.drop_first is not None and len(srv.requests) == 1:
                    self.wfile.write(body[:srv.drop_first])
                    self.wfile.flush()
                    self.close_connection = True
                    return
                self.wfile.write(body)

        self.httpd = ThreadingHTTPServer(("127.0.0.1", 0), Handler)
        self.thread = threading.Thread(target=self.httpd.serve_forever, daemon=True)

    def url(self, path: str) -> str:
        return f"http://127.0.0.1:{self.httpd.server_address[1]}{path}"

    def __enter__(self) -> "Server":
        self.thread.start()
        return self

    def __exit__(self, *exc) -> None:
        self.httpd.shutdown()
        self.httpd.server_close()


def tum_archive(tmp: Path) -> bytes:
    src = tmp / "src"
    write_tum(src / TUM_NAME, n=6)
    buf = io.BytesIO()
    with tarfile.open(fileobj=buf, mode="w:gz") as tf:
        tf.add(src / TUM_NAME, arcname=TUM_NAME)
    return buf.getvalue()


def seven_scenes_archive(tmp: Path) -> bytes:
    outer = io.BytesIO()
    with zipfile.ZipFile(outer, "w") as zf:
        for seq in ("seq-01", "seq-02"):
            write_frames(tmp / "src" / seq, range(4))
            inner = io.BytesIO()
            with zipfile.ZipFile(inner, "w") as z2:
                for p in sorted((tmp / "src" / seq).iterdir()):
                    z2.write(p, f"{seq}/{p.name}")
            zf.writestr(f"chess/{seq}.zip", inner.getvalue())
        zf.writestr("chess/TrainSplit.txt", "sequence1\n")
    return outer.getvalue()


def run(name: str, to: Path, url: str, *extra: str) -> int:
    return cli.main(["data", "download", name, "--to", str(to), "--url", url, "--quiet", *extra])


def leftovers(to: Path) -> list[str]:
    return sorted(str(p.relative_to(to)) for p in to.rglob("*")) if to.exists() else []


def test_interrupted_download_resumes_with_range(tmp_path: Path, capsys: pytest.CaptureFixture,
                                                 monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("CERPE_CACHE", str(tmp_path / "cache"))
    data = tum_archive(tmp_path)
    to = tmp_path / "data"
    with Server({f"/{TUM_NAME}.tgz": data}, drop_first=len(data) // 2) as srv:
        url = srv.url(f"/{TUM_NAME}.tgz")
        assert run("fr1/xyz", to, url, "--retries", "0") == 2
        err = capsys.readouterr()
        assert f"interrupted after {len(data) // 2} of {len(data)} bytes" in err.err and "rerun" in err.err
        assert "CC BY 4.0" in err.out  # the licence comes first
        part = to / ".downloads" / f"{TUM_NAME}.tgz.part"
        assert part.stat().st_size == len(data) // 2 and not (to / TUM_NAME).exists()
        assert run("fr1/xyz", to, url, "--sha256", hashlib.sha256(data).hexdigest()) == 0
        assert srv.requests[1] == (f"/{TUM_NAME}.tgz", f"bytes={len(data) // 2}-")  # resumed, not restarted
    out = capsys.readouterr().out
    folder = to / TUM_NAME
    assert finished(folder)["sha256"] == hashlib.sha256(data).hexdigest()
    assert leftovers(to / ".downloads") == []  # archive removed after unpacking
    # the printed manifest lines read the sequence as it is
    manifest = out.split("then `cerpe check` it):\n", 1)[1]
    (tmp_path / "m.yaml").write_text(manifest)
    doc = yaml.safe_load(manifest)
    assert doc["adapter"] == "tum-rgbd" and doc["data_root"] == str(folder.resolve())
    # the fixture's camera.yaml stands in for fr1's (its images are not 640x480)
    for rob in doc["encounters"][0]["robots"]:
        rob["camera"] = "camera.yaml"
    (tmp_path / "m.yaml").write_text(yaml.safe_dump(doc))
    (enc,) = load_setting(tmp_path / "m.yaml").encounters
    assert enc.n_steps == 3 and enc.robot_ids == ["first", "second"]
    # a second run finds the finished folder and fetches nothing
    with Server({}) as srv:
        assert run("fr1/xyz", to, srv.url("/x.tgz")) == 0 and srv.requests == []


def test_dropped_connection_is_resumed_within_one_call(tmp_path: Path) -> None:
    data = tum_archive(tmp_path)
    with Server({"/a.tgz": data}, drop_first=1000) as srv:
        assert run("freiburg1_xyz", tmp_path / "d", srv.url("/a.tgz"), "--retries", "1") == 0
        assert [r for _, r in srv.requests] == [None, "bytes=1000-"]
    assert finished(tmp_path / "d" / TUM_NAME) is not None


def test_server_without_ranges_restarts_from_zero(tmp_path: Path) -> None:
    data = tum_archive(tmp_path)
    with Server({"/a.tgz": data}, drop_first=1000, ranges=False) as srv:
        assert run("fr1/xyz", tmp_path / "d", srv.url("/a.tgz"), "--retries", "1") == 0
    assert finished(tmp_path / "d" / TUM_NAME) is not None


def test_checksum_mismatch_is_refused(tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    data = tum_archive(tmp_path)
    to = tmp_path / "d"
    with Server({"/a.tgz": data}) as srv:
        assert run("fr1/xyz", to, srv.url("/a.tgz"), "--sha256", "0" * 64) == 2
    err = capsys.readouterr().err
    assert "does not match the expected" in err and hashlib.sha256(data).hexdigest() in err
    assert leftovers(to) == [".downloads"]  # nothing half-written: no .part, no archive, no folder


def test_truncated_archive_is_refused(tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    data = tum_archive(tmp_path)
    to = tmp_path / "d"
    with Server({"/a.tgz": data[: len(data) * 2 // 3]}) as srv:  # a whole download of a cut archive
        assert run("fr1/xyz", to, srv.url("/a.tgz")) == 2
    assert "truncated or corrupt" in capsys.readouterr().err
    assert leftovers(to) == [".downloads"]


def test_seven_scenes_zip_with_sequence_zips(tmp_path: Path, capsys: pytest.CaptureFixture,
                                             monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("CERPE_CACHE", str(tmp_path / "cache"))
    with Server({"/chess.zip": seven_scenes_archive(tmp_path)}) as srv:
        assert run("7-scenes/chess", tmp_path / "d", srv.url("/chess.zip"), "--keep-archive") == 0
    folder = tmp_path / "d" / "chess"
    assert (folder / "seq-01" / "frame-000003.pose.txt").is_file() and not (folder / "seq-01.zip").exists()
    assert (tmp_path / "d" / ".downloads" / "chess.zip").is_file()
    out = capsys.readouterr().out
    assert "non-commercial" in out
    doc = yaml.safe_load(out.split("then `cerpe check` it):\n", 1)[1])
    doc["intrinsics"] = {"fx": 40.0, "fy": 41.0, "cx": 23.5, "cy": 17.5}  # the fixture's camera
    (tmp_path / "m.yaml").write_text(yaml.safe_dump(doc))
    (enc,) = load_setting(tmp_path / "m.yaml").encounters
    assert enc.robot_ids == ["seq-01", "seq-02"] and enc.n_steps == 4


def test_unsafe_member_and_unknown_names(tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w") as zf:
        zf.writestr("../evil.txt", "x")
    (tmp_path / "evil.zip").write_bytes(buf.getvalue())
    with pytest.raises(DownloadError, match="outside"):
        extract(tmp_path / "evil.zip", tmp_path / "out", "evil")
    assert not (tmp_path / "evil.txt").exists() and leftovers(tmp_path / "out") == []
    for bad in ("fr1/desk3", "7-scenes/kitchen", "kitti/00"):
        assert cli.main(["data", "download", bad, "--to", str(tmp_path)]) == 2
        assert "unknown" in capsys.readouterr().err
    with Server({}) as srv:
        with pytest.raises(DownloadError, match="HTTP 404"):
            fetch(srv.url("/missing.tgz"), tmp_path / "x.tgz", progress=False)
    assert not (tmp_path / "x.tgz.part").exists()


def test_catalogue_names_and_addresses() -> None:
    for name in ("fr1/xyz", "freiburg1_xyz", "rgbd_dataset_freiburg1_xyz", "tum-rgbd/freiburg1_xyz"):
        e = lookup(name)
        assert e.url == "https://cvg.cit.tum.de/rgbd/dataset/freiburg1/rgbd_dataset_freiburg1_xyz.tgz"
        assert e.folder == TUM_NAME and e.family == "tum-rgbd"
    e = lookup("7-scenes/chess")
    assert e.url.endswith("/28564B23-0828-408F-8631-23B1EFF1DAC8/chess.zip") and e.nested_zips
    assert "frames" in manifest_lines(e, Path("/nowhere/chess"))


def test_data_list_states_licences(capsys: pytest.CaptureFixture) -> None:
    assert cli.main(["data", "list"]) == 0
    out = capsys.readouterr().out
    assert "CC BY 4.0" in out and "non-commercial" in out and "long_office_household" in out and "redkitchen" in out
    assert MARKER.startswith(".")

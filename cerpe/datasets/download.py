"""Fetch and unpack a dataset archive: resumable HTTP download, size/checksum check, safe extraction.

Pure mechanics (no catalogue; see :mod:`cerpe.datasets.data_cli`):

* :func:`fetch` downloads ``url`` to ``dest`` through ``dest.part``. An interrupted
  transfer keeps the ``.part`` file and the next call resumes it with an HTTP
  ``Range`` request (a server that ignores ranges sends the whole file again).
  The size is checked against the server's ``Content-Length``/``Content-Range``
  (and ``size`` when given), the SHA-256 against ``sha256`` when given. A file that
  fails either is deleted, never renamed to ``dest``.
* :func:`extract` unpacks a ``.tar[.gz|.bz2|.xz]``/``.tgz`` or ``.zip`` into a hidden
  ``.partial`` folder, optionally with the ``.zip`` files inside it (7-Scenes ships one
  per sequence). It refuses members that would land outside the folder, then renames
  the result into place with a completion marker inside. A truncated or corrupt
  archive is an error that leaves nothing behind.
"""
from __future__ import annotations

import hashlib
import http.client
import json
import os
import shutil
import tarfile
import time
import urllib.error
import urllib.request
import zipfile
import zlib
from pathlib import Path

from tqdm import tqdm

from ..errors import CerpeError

MARKER = ".cerpe-download.json"  # inside a finished dataset folder: what was downloaded, with its checksum
CHUNK = 1 << 16


class DownloadError(CerpeError, ValueError):
    """A download or extraction failed; the message names the URL or file and what to do."""


def sha256_of(path: Path) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as fh:
        for block in iter(lambda: fh.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


def _total_from(resp: http.client.HTTPResponse, have: int) -> tuple[int, int | None]:
    """``(offset the body starts at, total size or None)`` of a 200/206 response."""
    if resp.status == 206:
        rng = resp.headers.get("Content-Range", "")  # "bytes START-END/TOTAL"
        try:
            start = int(rng.split()[1].split("-")[0])
            total = rng.rsplit("/", 1)[1]
            return start, None if total == "*" else int(total)
        except (IndexError, ValueError):
            raise DownloadError(f"the server sent a malformed Content-Range {rng!r}") from None
    length = resp.headers.get("Content-Length")
    return 0, int(length) if length and length.isdigit() else None


def fetch(url: str, dest: Path, sha256: str | None = None, size: int | None = None, retries: int = 2,
          timeout_s: float = 30.0, progress: bool = True) -> Path:
    """Download ``url`` to ``dest`` (resuming ``dest.part``), check size and checksum; returns ``dest``.

    Args:
        sha256: expected hex digest (None: computed and reported, not checked).
        size: expected size in bytes (None: the server's word is checked only).
        retries: further attempts after a dropped connection within this call (each resumes).

    Raises:
        DownloadError: HTTP errors, an interruption after ``retries`` (the ``.part`` file
            stays for the next call to resume), a size or checksum mismatch (file removed).
    """
    dest = Path(dest)
    dest.parent.mkdir(parents=True, exist_ok=True)
    part = dest.with_name(dest.name + ".part")
    total: int | None = None
    for attempt in range(retries + 1):
        have = part.stat().st_size if part.is_file() else 0
        headers = {"User-Agent": "cerpe-data-download"} | ({"Range": f"bytes={have}-"} if have else {})
        try:
            resp = urllib.request.urlopen(urllib.request.Request(url, headers=headers), timeout=timeout_s)
        except urllib.error.HTTPError as exc:
            if exc.code == 416 and have:  # nothing left to send: the .part may already be whole
                rng = exc.headers.get("Content-Range", "")
                total = int(rng.rsplit("/", 1)[1]) if "/" in rng and rng.rsplit("/", 1)[1].isdigit() else have
                break
            raise DownloadError(f"{url}: HTTP {exc.code} {exc.reason}") from None
        except (urllib.error.URLError, OSError) as exc:
            if attempt < retries:
                time.sleep(min(2.0 ** attempt, 10.0))
                continue
            raise DownloadError(f"{url}: cannot connect ({getattr(exc, 'reason', exc)}); rerun the same command to resume") from None
        with resp:
            start, total = _total_from(resp, have)
            if start != have:  # the server ignored the range (or sent another one): start over
                have = 0
            with open(part, "ab" if have else "wb") as out, tqdm(
                    total=total, initial=have, unit="B", unit_scale=True, desc=dest.name, disable=not progress,
                    leave=False) as bar:
                try:
                    for block in iter(lambda: resp.read(CHUNK), b""):
                        out.write(block)
                        bar.update(len(block))
                except (http.client.HTTPException, OSError):
                    pass  # a dropped connection: judged by the size below
        got = part.stat().st_size
        if total is None or got == total:
            break
        if got > total:
            part.unlink()
            raise DownloadError(f"{url}: received {got} bytes, more than the {total} announced; removed, rerun to download again")
        if attempt == retries:
            raise DownloadError(f"{url}: interrupted after {got} of {total} bytes; the partial file {part} is kept: "
                                "rerun the same command to resume")
    got = part.stat().st_size
    if size is not None and got != size:
        part.unlink()
        raise DownloadError(f"{url}: {got} bytes, expected {size}; the download was removed")
    if sha256 is not None:
        digest = sha256_of(part)
        if digest.lower() != sha256.lower():
            part.unlink()
            raise DownloadError(f"{url}: SHA-256 {digest} does not match the expected {sha256}; the download was removed")
    os.replace(part, dest)
    return dest


def _archive_kind(path: Path) -> str:
    name = path.name.lower()
    if name.endswith(".zip"):
        return "zip"
    if name.endswith((".tgz", ".tar", ".tar.gz", ".tar.bz2", ".tar.xz", ".tbz2", ".txz")):
        return "tar"
    raise DownloadError(f"{path}: unknown archive type (expected .zip, .tar, .tgz, .tar.gz, .tar.bz2 or .tar.xz)")


def _unzip(path: Path, into: Path) -> None:
    root = into.resolve()
    with zipfile.ZipFile(path) as zf:
        for info in zf.infolist():
            target = (into / info.filename).resolve()
            if info.filename.startswith("/") or not target.is_relative_to(root):
                raise DownloadError(f"{path}: member {info.filename!r} would be written outside the target folder")
        zf.extractall(into)


def extract(archive: Path, into: Path, name: str, nested_zips: bool = False, meta: dict | None = None) -> Path:
    """Unpack ``archive`` into ``into`` and return the dataset folder (``into/<top folder>``).

    An archive with one top-level folder keeps its name; otherwise its members are
    put into ``into/name``. With ``nested_zips`` the ``.zip`` files found inside are
    unpacked next to themselves and removed. ``meta`` (plus the archive's SHA-256 and
    size) goes into the completion marker :data:`MARKER`.

    Raises:
        DownloadError: a truncated/corrupt archive (nothing is left behind), unsafe
            member names, or a target folder that exists without a completion marker.
    """
    kind = _archive_kind(archive)
    tmp = into / f".{archive.name}.partial"
    shutil.rmtree(tmp, ignore_errors=True)
    tmp.mkdir(parents=True)
    try:
        if kind == "tar":
            with tarfile.open(archive, "r:*") as tf:
                tf.extractall(tmp, filter="data")
        else:
            _unzip(archive, tmp)
        if nested_zips:
            for inner in sorted(tmp.rglob("*.zip")):
                _unzip(inner, inner.parent)
                inner.unlink()
    except (tarfile.TarError, zipfile.BadZipFile, EOFError, zlib.error, OSError, DownloadError) as exc:
        shutil.rmtree(tmp, ignore_errors=True)
        if isinstance(exc, DownloadError):
            raise
        raise DownloadError(f"{archive}: the archive is truncated or corrupt ({exc}); nothing was extracted") from None
    entries = [p for p in tmp.iterdir()]
    if len(entries) == 1 and entries[0].is_dir():
        src, final = entries[0], into / entries[0].name
    else:
        src, final = tmp, into / name
    if final.exists():
        shutil.rmtree(tmp, ignore_errors=True)
        raise DownloadError(f"{final} exists but is not a finished download (no {MARKER}); move it away and rerun")
    marker = {**(meta or {}), "archive": archive.name, "sha256": sha256_of(archive), "bytes": archive.stat().st_size}
    (src / MARKER).write_text(json.dumps(marker, indent=1) + "\n")
    os.replace(src, final)
    shutil.rmtree(tmp, ignore_errors=True)
    return final


def finished(folder: Path) -> dict | None:
    """The completion marker of a dataset folder, None when it is absent (not a finished download)."""
    try:
        return json.loads((folder / MARKER).read_text())
    except (OSError, ValueError):
        return None

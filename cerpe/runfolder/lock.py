"""One writer per run folder: an exclusive ``flock`` on ``RUNDIR/run.lock``.

The process that writes a folder holds the lock from before it reads ``run.json`` until it is
done; a second writer stops at once with :class:`RunBusy` naming the folder and the holder (pid,
host, command, written into the lock file), or waits for it (``wait=True``, ``cerpe run --wait``).
The operating system drops the lock when its file closes, so it is released on exit, on Ctrl-C
and when the process crashes or is killed: a lock file left behind holds nothing. Readers
(``cerpe eval``, is-current checks) never take it. Where ``fcntl`` does not exist (Windows) there
is no lock.
"""
from __future__ import annotations

import logging
import os
import socket
import sys
from pathlib import Path
from typing import IO

from ..atomicio import ensure_dir
from .layout import LOCK_FILE, RunError

log = logging.getLogger(__name__)


class RunBusy(RunError):
    """Another process is writing the run folder."""


def holder_text() -> str:
    """What this process writes into the lock it holds: ``pid N on HOST: COMMAND``."""
    return f"pid {os.getpid()} on {socket.gethostname()}: {' '.join(sys.argv) or 'python'}"


class RunLock:
    """The write lock of run folder ``folder`` (created if missing); a context manager.

    ``wait``: block until the holder is done instead of raising :class:`RunBusy`.
    """

    def __init__(self, folder: Path | str, wait: bool = False) -> None:
        self.folder = Path(folder)
        self.path = self.folder / LOCK_FILE
        self.wait = bool(wait)
        self._fh: IO[str] | None = None
        self._created = False

    @property
    def held(self) -> bool:
        return self._fh is not None

    def acquire(self) -> "RunLock":
        if self._fh is not None:
            return self
        try:
            import fcntl
        except ImportError:  # not POSIX: no lock
            return self
        while True:
            self._created = not self.folder.exists()
            ensure_dir(self.folder, "--out")
            fh = open(self.path, "a+")
            try:
                try:
                    fcntl.flock(fh, fcntl.LOCK_EX | fcntl.LOCK_NB)
                except BlockingIOError:
                    holder = self._holder(fh)
                    if not self.wait:
                        raise RunBusy(f"--out {self.folder} is busy: {holder} is writing it (lock {self.path}); "
                                      f"wait for it to finish, or add --wait to start when it has") from None
                    log.warning("%s is busy (%s); waiting for it", self.folder, holder)
                    fcntl.flock(fh, fcntl.LOCK_EX)
                if not self._same_file(fh):  # the holder removed the file it held: lock the new one
                    fh.close()
                    continue
                fh.seek(0)
                fh.truncate()
                fh.write(holder_text() + "\n")
                fh.flush()
            except BaseException:
                fh.close()
                raise
            self._fh = fh
            return self

    def _same_file(self, fh: IO[str]) -> bool:
        try:
            return os.stat(self.path).st_ino == os.fstat(fh.fileno()).st_ino
        except FileNotFoundError:
            return False

    @staticmethod
    def _holder(fh: IO[str]) -> str:
        fh.seek(0)
        text = fh.read().strip().splitlines()
        return text[0] if text else "another process"

    def release(self) -> None:
        """Drop the lock (closing the file drops it; the file stays, holding nothing). A folder this lock
        created that holds nothing else (the run failed before writing ``run.json``) is removed."""
        if self._fh is None:
            return
        try:
            if self._created and [p.name for p in self.folder.iterdir()] == [LOCK_FILE]:
                self.path.unlink()
                self.folder.rmdir()
        except OSError:  # another process put something there meanwhile: leave it
            pass
        finally:
            self._fh.close()
            self._fh = None

    def __enter__(self) -> "RunLock":
        return self.acquire()

    def __exit__(self, *exc: object) -> None:
        self.release()

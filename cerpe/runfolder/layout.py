"""Names of a run folder's files and columns, its format version, and the error of an unusable folder.

``RUN_FORMAT`` is the version of the layout and of ``run.json``: a folder of another format is
never reused nor extended (``cerpe run`` says to rerun it with ``--overwrite``).
"""
from __future__ import annotations

from ..errors import CerpeError

RUN_FORMAT = 2

RUN_JSON = "run.json"
LOCK_FILE = "run.lock"
DONE_JSON = "DONE.json"
STEPS_CSV = "steps.csv"
ROBOTS_CSV = "robots.csv"
PEER_OVERLAP_CSV = "peers_overlap.csv"  # an online robot's folder: its peers' overlap_gt rows about it (FRAME_KEY)

POSE = ("tx", "ty", "tz", "qx", "qy", "qz", "qw")  # pose columns <prefix>_tx .. <prefix>_qw (est, gt, ...)
FRAME_KEY = ("encounter", "step", "ego", "other")
REQUIRED_STEP_COLS = ("encounter", "step", "stamp_s", "ego", "other", "source",
                      *(f"est_{c}" for c in POSE), *(f"gt_{c}" for c in POSE))


class RunError(CerpeError, ValueError):
    """Bad run request or a run folder that cannot be used (other configuration, corrupt file, busy)."""

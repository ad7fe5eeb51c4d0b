"""Shared pytest fixtures (kept small on purpose)."""
from __future__ import annotations

import os
import sys
from pathlib import Path

import pytest
from hypothesis import settings

# Property tests draw the same examples on every run (derandomize), so a CI run passes or fails by the
# code, not by the draw; HYPOTHESIS_PROFILE=explore draws new ones (and keeps a local example database).
# Loaded here, before the test modules build their settings(...) from the default profile.
settings.register_profile("cerpe", derandomize=True, database=None)
settings.register_profile("explore", derandomize=False)
settings.load_profile(os.environ.get("HYPOTHESIS_PROFILE", "cerpe"))

TESTS_DIR = Path(__file__).resolve().parent
if str(TESTS_DIR) not in sys.path:  # lets tests import the doubles in tests/gt_backbone.py
    sys.path.insert(0, str(TESTS_DIR))
if str(TESTS_DIR.parent) not in sys.path:  # and the development studies, `lab` (not installed)
    sys.path.append(str(TESTS_DIR.parent))

SHARED_DATA = TESTS_DIR.parents[0].parent / "shared" / "data"


@pytest.fixture
def shared_data() -> Path:
    """``../shared/data`` next to the repository root; skips the test when absent."""
    if not SHARED_DATA.is_dir():
        pytest.skip(f"shared data not present at {SHARED_DATA}")
    return SHARED_DATA

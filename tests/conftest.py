"""Shared pytest fixtures (kept small on purpose)."""
from __future__ import annotations

import sys
from pathlib import Path

import pytest

TESTS_DIR = Path(__file__).resolve().parent
if str(TESTS_DIR) not in sys.path:  # lets tests import the doubles in tests/gt_backbone.py
    sys.path.insert(0, str(TESTS_DIR))

SHARED_DATA = TESTS_DIR.parents[0].parent / "shared" / "data"


@pytest.fixture
def shared_data() -> Path:
    """``../shared/data`` next to the repository root; skips the test when absent."""
    if not SHARED_DATA.is_dir():
        pytest.skip(f"shared data not present at {SHARED_DATA}")
    return SHARED_DATA

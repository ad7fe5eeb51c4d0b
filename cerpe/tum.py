"""TUM trajectory text, the one writer (``cerpe.datasets.formats.read_trajectory`` reads it).

Kept out of ``cerpe.datasets`` so that the synthetic writer, the run folders and the
dataset adapters share it without depending on each other.
"""
from __future__ import annotations

import numpy as np

from .geometry import se3_to_tq_xyzw

__all__ = ["format_tum"]


def format_tum(stamps_s: np.ndarray, T: np.ndarray,
               header: str = "timestamp tx ty tz qx qy qz qw", stamp_decimals: int = 9) -> str:
    """TUM trajectory text, ``stamp tx ty tz qx qy qz qw`` per pose ``T [N,4,4]``.

    Quaternions scalar-last; evo and :func:`read_trajectory` (``fmt="tum"``) read it unchanged.
    """
    lines = [f"# {header}"]
    for s, Tk in zip(stamps_s, T):
        t, q = se3_to_tq_xyzw(Tk)
        lines.append(f"{s:.{stamp_decimals}f} " + " ".join(f"{v:.9f}" for v in (*t, *q)))
    return "\n".join(lines) + "\n"

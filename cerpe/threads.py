"""How many threads torch may use inside one operation (intra-op), for every model cerpe runs.

Why one setting, and why 1 by default: a convolution or attention on the CPU gives
results that differ in the last bits with the number of intra-op threads. ALIKED
keypoints and LightGlue matches of the same images hash differently at 1 and 2
threads, and those bits can flip a RANSAC or gate decision. With one fixed count the
tables do not depend on the number of cores or on ``cerpe paper --jobs N``. Parallelism
comes from worker processes instead, which are no slower than more threads per process.

``CERPE_THREADS`` (environment) or a model's ``num_threads`` conf key overrides it,
e.g. for one robot's online process on a many-core computer.
"""
from __future__ import annotations

import os

from .errors import CerpeError

#: intra-op threads when neither a conf key nor ``CERPE_THREADS`` says otherwise
DEFAULT_THREADS = 1
ENV = "CERPE_THREADS"


class ThreadsError(CerpeError, ValueError):
    """A thread count that is not a positive integer."""


def torch_threads(num_threads: int | None = None) -> int:
    """The intra-op thread count: ``num_threads`` if given, else ``$CERPE_THREADS``, else 1."""
    raw: object = num_threads if num_threads is not None else os.environ.get(ENV, DEFAULT_THREADS)
    try:
        n = int(raw)  # type: ignore[arg-type]
    except (TypeError, ValueError):
        n = 0
    if n < 1:
        where = "num_threads" if num_threads is not None else ENV
        raise ThreadsError(f"{where}={raw!r}: expected a positive integer number of threads")
    return n


def apply_torch_threads(num_threads: int | None = None) -> int:
    """Set torch's intra-op thread count (process-wide) to :func:`torch_threads`; returns it."""
    import torch

    n = torch_threads(num_threads)
    if torch.get_num_threads() != n:
        torch.set_num_threads(n)
    return n

"""How many threads torch (intra-op) and numpy's BLAS may use inside one operation.

Why one setting, and why 1 by default: a convolution or attention on the CPU gives
results that differ in the last bits with the number of intra-op threads. ALIKED
keypoints and LightGlue matches of the same images hash differently at 1 and 2
threads, and those bits can flip a RANSAC or gate decision. With one fixed count the
tables do not depend on the number of cores or on ``cerpe paper --jobs N``. Parallelism
comes from worker processes instead, which are no slower than more threads per process.

``CERPE_THREADS`` (environment) or a model's ``num_threads`` conf key overrides it,
e.g. for one robot's online process on a many-core computer.

numpy's BLAS (OpenBLAS) gets the same count, through ``threadpoolctl``. Left to itself it starts a
thread per core, and those threads spin after each matrix product: in ``cerpe bench`` they burned
100 ms of CPU per robot-step on the core a registration worker needed. ``make`` already sets
``OMP_NUM_THREADS=1``, which OpenBLAS reads at start-up. :func:`apply_threads` runs when XFeat or
LightGlue is built and at the start of ``cerpe bench``, so those commands run bare as under ``make``;
a command that builds neither (a SIFT-only ``cerpe run``) keeps OpenBLAS's own count.
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


def apply_threads(num_threads: int | None = None) -> int:
    """Set torch's intra-op and numpy's BLAS thread counts (process-wide) to :func:`torch_threads`;
    returns it."""
    import torch

    n = torch_threads(num_threads)
    if torch.get_num_threads() != n:
        torch.set_num_threads(n)
    if blas_threads() != n:
        from threadpoolctl import threadpool_limits

        threadpool_limits(limits=n, user_api="blas")  # kept: not used as a context manager
    return n


def blas_threads() -> int | None:
    """The most threads numpy's BLAS libraries use now (None: no BLAS found)."""
    from threadpoolctl import threadpool_info

    counts = [int(i["num_threads"]) for i in threadpool_info() if i.get("user_api") == "blas"]
    return max(counts) if counts else None

"""One BLAS thread policy for every pmcal entry point (CLI, Python API, benchmarks).

pmcal's dense linear algebra works on small matrices (a few hundred rows, tens of columns, stacks of
6x6 normal equations). At these sizes OpenBLAS threads cost more than they save, and next to another
busy process (a second pmcal job, MuJoCo's own thread pool, pytest-xdist) their spin-waiting makes a
whole-chain identification 15-40x slower. The policy: one BLAS thread per process, unless overridden
by the environment variable ``PMCAL_BLAS_THREADS`` (a positive integer, or ``0``/``default`` to leave
the libraries' own setting alone) or by the ``n`` argument.

Uses ``threadpoolctl`` (numpy's and scipy's bundled OpenBLAS, MKL, BLIS alike). Foundation module:
imports nothing else of pmcal.
"""

from __future__ import annotations

from contextlib import contextmanager
from functools import lru_cache

import os

#: Environment variable that overrides the policy: a positive thread count, or 0 / "default".
ENV_VAR = "PMCAL_BLAS_THREADS"
#: Threads per process when neither the caller nor the environment says otherwise.
DEFAULT_THREADS = 1

_limiter = None
#: the thread count :func:`apply_blas_policy` set for the whole process (None: none set)
_applied = None


def policy_threads(n: int | None = None) -> int | None:
    """BLAS threads the policy asks for: ``n``, else ``$PMCAL_BLAS_THREADS``, else 1 (None: no limit).

    Raises ValueError naming the variable when its value is not a non-negative integer or "default".
    """
    source = f"BLAS threads {n!r}"
    if n is None:
        text = os.environ.get(ENV_VAR, "").strip().lower()
        if not text:
            return DEFAULT_THREADS
        if text == "default":
            return None
        source = f"{ENV_VAR}={text!r}"
        try:
            n = int(text)
        except ValueError:
            n = -1
    if int(n) != n or n < 0:
        raise ValueError(f"{source}: expected a thread count (>= 1), 0 or 'default'")
    return None if n == 0 else int(n)


def apply_blas_policy(n: int | None = None) -> int | None:
    """Limit the BLAS libraries of this process to the policy's thread count (see :func:`policy_threads`).

    Call it once at an entry point, after numpy/scipy are importable; calling it again re-applies the
    (possibly new) limit. Returns the thread count set (None: libraries left at their own setting).
    """
    global _limiter, _applied
    count = policy_threads(n)
    import numpy  # noqa: F401  (load the libraries the limit applies to)
    import scipy.linalg  # noqa: F401
    from threadpoolctl import threadpool_limits

    if _limiter is not None:
        _limiter.restore_original_limits()
        _limiter = None
    if count is not None:
        _limiter = threadpool_limits(limits=count, user_api="blas")
    _applied = count
    return count


def blas_threads() -> list[int]:
    """Thread counts of the BLAS libraries loaded in this process (for reports and benchmarks)."""
    from threadpoolctl import threadpool_info

    return [int(i["num_threads"]) for i in threadpool_info() if i.get("user_api") == "blas"]


@lru_cache(maxsize=1)
def _controller():
    """threadpoolctl's view of the BLAS libraries loaded with numpy and scipy, found once per process:
    finding them scans the process's shared objects (~1-2 ms), which a per-call limit would repeat on
    every identification (the planar campaign's whole fit takes about that long)."""
    import numpy  # noqa: F401  (load the libraries the limit applies to)
    import scipy.linalg  # noqa: F401
    from threadpoolctl import ThreadpoolController

    return ThreadpoolController()


@contextmanager
def blas_policy(n: int | None = None):
    """The policy's thread limit for the duration of a block (or of a decorated function), restored after.

    The library's heavy entry points (:func:`pmcal.identify`, :meth:`pmcal.Calibration.setpoints`,
    :meth:`pmcal.Calibration.compensation_table`) run under it, so a script or notebook gets the same
    policy as the command line without a process-wide side effect.
    """
    count = policy_threads(n)
    if count is None or (_limiter is not None and _applied == count):   # the process already holds it
        yield
        return
    with _controller().limit(limits=count, user_api="blas"):
        yield

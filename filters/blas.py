"""How many threads the BLAS libraries use while the filters' linear algebra runs.

OpenBLAS starts one thread per core by default. The filters' matrices are small (a few hundred
rows at most), and with a second thread a dense factorisation is not faster but much slower as
soon as the other core is busy (as it is in a two-process training run): ``cho_factor`` of a
600 x 600 matrix took 318 ms against 6 ms with one thread, and an episode that optimised at
every decision ran at 45-48 decisions/s against 87 (issue 40). The project's CLI sets one BLAS
thread per process; a user who calls ``gym.make`` in their own process does not get that.

:func:`limited_blas_threads` limits the BLAS libraries loaded in this process to ``n`` threads
while a ``with`` block runs and restores their previous counts when it ends, so the limit holds only
inside the project's own calls (the optimiser, an env step) and leaves the user's other numpy
work alone; nothing changes at import. It acts on the libraries threadpoolctl finds at its
first use (numpy's and SciPy's OpenBLAS: this module imports both first). Each entry costs a
few microseconds when the libraries already use ``n`` threads and ~10 us when they must be
switched and switched back (docs/PERFORMANCE.md), against 3-10 ms for a decision of the env.
The count is process-wide: another thread of the user's process that calls BLAS during the
block runs with the limit too.
"""

from __future__ import annotations

import contextlib
import functools

import numpy as np  # noqa: F401  (loads numpy's BLAS before the libraries are listed)
import scipy.linalg  # noqa: F401  (loads SciPy's BLAS)

from filters.validation import require

DEFAULT_BLAS_THREADS = 1
"""The filters' default: one BLAS thread (module docstring)."""

MAX_BLAS_THREADS = 1024


def check_blas_threads(n, name: str = "blas_threads"):
    """``n``: None (leave the process's BLAS threads as they are) or an integer in [1, 1024];
    ``ValueError`` naming ``name`` otherwise."""
    require(
        n is None or (isinstance(n, (int, np.integer)) and not isinstance(n, bool)
                      and 1 <= n <= MAX_BLAS_THREADS),
        name, n, f"None or an integer in [1, {MAX_BLAS_THREADS}]",
    )
    return None if n is None else int(n)


@functools.cache
def _blas_libraries() -> tuple:
    """threadpoolctl's controllers of the BLAS libraries loaded now (listed once: scanning the
    process's libraries takes ~2 ms)."""
    from threadpoolctl import ThreadpoolController

    return tuple(lib for lib in ThreadpoolController().lib_controllers if lib.user_api == "blas")


@contextlib.contextmanager
def limited_blas_threads(n: int | None = DEFAULT_BLAS_THREADS):
    """Run the ``with`` block with ``n`` threads in every BLAS library, then restore their
    previous counts (module docstring). ``n=None`` changes nothing."""
    n = check_blas_threads(n)
    if n is None:
        yield
        return
    changed = []
    for lib in _blas_libraries():
        before = lib.get_num_threads()
        if before != n:
            lib.set_num_threads(n)
            changed.append((lib, before))
    try:
        yield
    finally:
        for lib, before in changed:
            lib.set_num_threads(before)


def blas_thread_counts() -> list[int]:
    """The thread count of each BLAS library loaded in this process now (tests, diagnostics)."""
    return [lib.get_num_threads() for lib in _blas_libraries()]

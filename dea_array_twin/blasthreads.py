"""Keep this process's BLAS on one thread: its products then run on the thread that calls them.

OpenBLAS spreads a large product over its own helper threads, which spin for ~0.1 s after
each call: a real-time process refreshing a reduced Hessian every few tens of ms would keep
the other core busy.  With one BLAS thread the product runs on the calling thread alone, so
the ROM's background refresh worker (:class:`~.model.reduced_twin.ReducedTwin`) can use BLAS
products (~4x faster than its point-by-point sum) and still leave the other core to the
updates (docs/rom.md).

NumPy's and SciPy's wheels each carry their own OpenBLAS (symbols with ``scipy_`` prefixes,
``64_`` suffixes for the 64-bit-integer build); a distribution's numpy links the system
OpenBLAS (plain ``openblas_set_num_threads``).  :func:`single_threaded_blas` sets every
loaded one.  threadpoolctl does the same for more libraries but has no rosdep key (docs/architecture.md).
Imports nothing of the package.
"""

from __future__ import annotations

import ctypes
import os

#: Entry points of OpenBLAS's thread count, as the wheels and the distributions build it.
_PREFIXES = ("openblas", "scipy_openblas")
_SUFFIXES = ("", "64_", "_64_")
#: Other BLAS libraries whose threads this module cannot set: with one loaded, nothing is promised.
_OTHER_BLAS = ("libmkl", "libblis", "libarmpl")


def loaded_libraries() -> list[str]:
    """Paths of the shared libraries mapped into this process (``/proc/self/maps``; empty elsewhere)."""
    try:
        with open("/proc/self/maps", encoding="utf-8", errors="replace") as maps:
            paths = {line.split(maxsplit=5)[5].strip() for line in maps if line.count(" ") >= 5 and ".so" in line}
    except OSError:
        return []
    return sorted(p for p in paths if p.startswith("/"))


def _set_one_thread(path: str) -> bool | None:
    """Set the OpenBLAS at ``path`` to one thread; None when it exports no thread count."""
    try:
        lib = ctypes.CDLL(path, mode=ctypes.RTLD_LOCAL | os.RTLD_NOLOAD)
    except OSError:
        return None
    for prefix in _PREFIXES:
        for suffix in _SUFFIXES:
            setter = getattr(lib, f"{prefix}_set_num_threads{suffix}", None)
            getter = getattr(lib, f"{prefix}_get_num_threads{suffix}", None)
            if setter is None or getter is None:
                continue
            setter.argtypes, setter.restype, getter.restype = [ctypes.c_int], None, ctypes.c_int
            setter(1)
            return getter() == 1
    return None


def single_threaded_blas() -> bool:
    """Set every OpenBLAS loaded in this process to one thread.

    Call it after numpy and scipy are imported (a library loaded later keeps its own count).

    Returns
    -------
    bool
        True when at least one OpenBLAS was found, each now reports one thread, and no
        other BLAS (MKL, BLIS, Arm PL) is loaded; False otherwise: then BLAS products may
        still run on helper threads.
    """
    libraries = loaded_libraries()
    if any(os.path.basename(p).startswith(_OTHER_BLAS) for p in libraries):
        return False
    answers = [_set_one_thread(p) for p in libraries if "openblas" in os.path.basename(p).lower()]
    found = [a for a in answers if a is not None]
    return bool(found) and all(found)

"""Helper threads that share a reduced update's evaluations with the thread calling it.

An evaluation of the hyper-reduced model streams every sampled point's maps from memory; on a
large ROM (the 4-by-4's are 11 MB) one core's bandwidth bounds it.  A :class:`PointTeam` has
helper threads that, once an update has woken them (``with team:``), spin in compiled code with
the GIL released and claim chunks of each pass's points (:data:`.rom_kernels.CHUNK`) by an atomic
compare-and-swap, as the calling thread does (:func:`.rom_kernels.update`), and go back to sleep
when no update has come for :data:`LINGER`.  They run under ``SCHED_IDLE``: only on CPU time no
other thread wants.  Each chunk's sums are its own and are added in chunk order, so the outputs
are the same whoever evaluated what, and the same as with no helper.

The caller never waits on a helper that has not started: it claims every chunk still free
itself.  A chunk a helper is evaluating is waited for at most :attr:`PointTeam.wait` (a few
chunks' time); a helper that the scheduler has taken off its core meanwhile loses the chunk
to the caller, who evaluates it again (:attr:`PointTeam.taken_over` counts those).
"""

from __future__ import annotations

import os
import threading
import time
import weakref

import numpy as np

from .rom_kernels import (
    _GRADIENT_DEFER,
    _HELPED,
    _LINGER,
    _RUNNING,
    _TAKEN,
    _WAIT,
    _pass,
    assist,
    team_arrays,
    wait_for,
)

#: At most this many threads (the caller and six helpers: a chunk's state codes fit in 4 bits).
MAX_THREADS = 7

#: The longest the caller waits for a chunk a helper is evaluating, in units of the time one chunk took
#: the caller alone (then it evaluates the chunk itself), and at least :data:`WAIT_FLOOR` seconds.
WAIT_CHUNKS = 3.0
WAIT_FLOOR = 20e-6
#: How long a helper keeps spinning after an update for the next before it sleeps [s]: at update rates above
#: ~1 / LINGER it never sleeps, so the caller neither wakes it (a system call) nor meets it holding the GIL.
LINGER = 2e-3


def _serve(points: tuple, arrays: tuple, wake: threading.Lock, stopped: list, thread: int) -> None:
    """A helper thread: sleep until woken, then assist (at the lowest priority, :func:`idle_priority`) until
    the updates stop coming; until stopped."""
    while True:
        wake.acquire()
        if stopped[0]:
            return
        idle_priority()
        assist(points, arrays, thread)


def idle_priority() -> None:
    """Put the calling thread under ``SCHED_IDLE`` (Linux): it runs only on CPU time no other thread of the
    machine wants (a refresh in the twin's worker, the node's executor, other processes), also when the
    process was put under ``SCHED_FIFO`` after the thread started (so a helper checks at every wake-up).
    Elsewhere, or if refused, nothing is done."""
    if not hasattr(os, "SCHED_IDLE"):
        return
    tid = threading.get_native_id()
    try:
        if os.sched_getscheduler(tid) != os.SCHED_IDLE:
            os.sched_setscheduler(tid, os.SCHED_IDLE, os.sched_param(0))
    except OSError:
        return


def _stop(control: np.ndarray, wakes: list, stopped: list, threads: list) -> None:
    stopped[0] = True
    control[_LINGER] = 0
    control[_RUNNING] = 0
    for wake, thread in zip(wakes, threads):
        if wake.locked():
            wake.release()
        if thread is not threading.current_thread():
            thread.join()


class PointTeam:
    """The calling thread of a reduced twin and ``n_threads - 1`` helper threads sharing its evaluations.

    Parameters
    ----------
    points : tuple
        ``(fmap, wmap, xi, unit, held, c10, c20, c30)`` as for :func:`.rom_kernels.update`.
    n_threads : int
        Threads in all, the caller included (1: no helper, the caller evaluates every chunk).
    n_units : int

    Attributes
    ----------
    arrays : tuple
        The :func:`.rom_kernels.team_arrays` to pass to :func:`.rom_kernels.update` and
        :func:`.rom_kernels.heights` inside ``with team:``.
    wait : float
        The longest the caller waits for a chunk a helper is evaluating [s].
    """

    def __init__(self, points: tuple, n_threads: int, n_units: int):
        if not 1 <= n_threads <= MAX_THREADS:
            raise ValueError(f"threads must be 1 to {MAX_THREADS}, got {n_threads}")
        fmap, wmap = points[0], points[1]
        self.n_threads = n_threads
        self.arrays = team_arrays(n_threads, fmap.shape[0], fmap.shape[2], wmap.shape[2], n_units)
        self.wait = 0.0
        self._wakes: list[threading.Lock] = []
        self._threads: list[threading.Thread] = []
        if n_threads == 1:
            return
        self.wait = self._set_wait(points, n_units)
        assist(points, self.arrays, 1)  # compiled (or loaded) here, not in the helper's first update
        stopped = [False]
        for t in range(1, n_threads):
            wake = threading.Lock()
            wake.acquire()
            thread = threading.Thread(target=_serve, args=(points, self.arrays, wake, stopped, t),
                                      name=f"rom-points-{t}", daemon=True)
            thread.start()
            self._wakes.append(wake)
            self._threads.append(thread)
        self._finalizer = weakref.finalize(self, _stop, self.arrays[0], self._wakes, stopped, self._threads)

    def _set_wait(self, points: tuple, nu: int) -> float:
        """Time one chunk of a pass by the caller alone, and the caller's wait loop; set the wait in spins."""
        fmap, wmap = points[0], points[1]
        nc, nw = fmap.shape[2], wmap.shape[2]
        z = np.zeros(nc)
        z[0] = 1.0
        out = (np.empty(nc), np.empty(nu), np.empty(nw), np.empty(nu))
        times = []
        for _ in range(3):
            start = time.perf_counter()
            _pass(*points, *self.arrays, _GRADIENT_DEFER, fmap.itemsize == 4, z, np.zeros(nu), *out)
            times.append(time.perf_counter() - start)
        chunk = min(times) / self.arrays[1].size
        never = np.zeros(1, dtype=np.int64)  # the caller's wait loop on a chunk that does not finish
        n = 100_000
        wait_for(never, 0, 1, 10)
        start = time.perf_counter()
        wait_for(never, 0, 1, n)
        per_spin = (time.perf_counter() - start) / n
        wait = max(WAIT_CHUNKS * chunk, WAIT_FLOOR)
        self.arrays[0][_WAIT] = max(1, int(wait / per_spin))
        self.arrays[0][_LINGER] = int(LINGER / per_spin)
        return wait

    def __enter__(self) -> "PointTeam":
        if self._wakes:
            self.arrays[0][_RUNNING] = 1
            for wake in self._wakes:
                if wake.locked():
                    try:
                        wake.release()
                    except RuntimeError:  # released by another thread between the check and here
                        pass
        return self

    def __exit__(self, *exc) -> None:
        self.arrays[0][_RUNNING] = 0

    @property
    def helped(self) -> int:
        """Chunks the helpers evaluated so far."""
        return int(self.arrays[0][_HELPED])

    @property
    def taken_over(self) -> int:
        """Chunks a helper had claimed that the caller evaluated itself (the helper was too slow)."""
        return int(self.arrays[0][_TAKEN])

    def close(self) -> None:
        """Stop the helper threads (also when the team is garbage collected)."""
        if self._threads:
            self._finalizer()

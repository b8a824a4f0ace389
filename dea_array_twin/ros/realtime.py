"""Real-time scheduling of the twin node's process (the ``realtime_priority`` parameter).

At 1 kHz a tick is 1 ms, and the solver thread's work per tick (take the commands,
update the reduced twin, publish three messages) is about 0.45 ms.  Under the normal
Linux scheduler a thread that wakes for its tick can wait a millisecond or more for a
core held by another process (on two cores, the controller sending the commands), and
ticks are lost although the work fits.  ``SCHED_FIFO`` runs a waking thread before any
normal one.  It has to cover every thread of the process, not only the solver: the
solver waits for the GIL and for DDS locks held by the executor's and the middleware's
threads, and one of those preempted while holding them delays it as much
(``benchmarks/bench_rom.py --node``: the solver thread alone under ``SCHED_FIFO`` held
95-99 % of the ticks, the whole process 99.5-99.7 %, against 95-98 % without).

So :func:`use_fifo` puts every thread the process has under ``SCHED_FIFO`` and, since a
new thread inherits its creator's policy, every thread started after it.  This is what
ROS 2 controllers do (ros2_control's ``thread_priority``); it needs ``CAP_SYS_NICE`` or
an ``rtprio`` limit for the user (``/etc/security/limits.conf``), and the kernel keeps
5 % of each second for normal threads (``/proc/sys/kernel/sched_rt_runtime_us``).
"""

from __future__ import annotations

import os

#: Highest ``SCHED_FIFO`` priority Linux accepts.
MAX_PRIORITY = 99


def use_fifo(priority: int) -> int:
    """Put every thread of this process, and so every thread it starts later, under ``SCHED_FIFO``.

    Parameters
    ----------
    priority : int
        1 to :data:`MAX_PRIORITY`.

    Returns
    -------
    int
        The number of threads changed.

    Raises
    ------
    ValueError
        ``priority`` is out of range.
    PermissionError
        The process may not use real-time scheduling (no ``CAP_SYS_NICE``, ``rtprio``
        limit below ``priority``); no thread was changed.
    OSError
        Another refusal by the kernel, or no ``SCHED_FIFO`` on this system.
    """
    if not 1 <= priority <= MAX_PRIORITY:
        raise ValueError(f"realtime priority must be 1-{MAX_PRIORITY}, got {priority}")
    if not hasattr(os, "SCHED_FIFO"):
        raise OSError("SCHED_FIFO is not available on this system")
    threads = sorted(int(t) for t in os.listdir("/proc/self/task"))
    main = os.getpid()
    param = os.sched_param(priority)
    os.sched_setscheduler(main, os.SCHED_FIFO, param)  # refused as a whole here, before any other thread
    changed = 1
    for tid in threads:
        if tid == main:
            continue
        try:
            os.sched_setscheduler(tid, os.SCHED_FIFO, param)
            changed += 1
        except ProcessLookupError:  # a thread that ended meanwhile
            continue
    return changed

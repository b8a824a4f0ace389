"""The machine's floor for a periodic Python thread: what share of its ticks a bare thread holds.

A node's "ticks held" is bounded by how punctually the machine wakes a Python thread:
this thread waits on a ``threading.Condition`` for each next tick, as the node's solver
thread does (``ros/updater.py``), does nothing else, and counts a tick as lost when it
woke a whole period late.  ``bench_core.py --node`` and ``bench_rom.py --node`` print it
beside the node's figures (the same rate and scheduling), so that a node's share can be
read against what the machine gave a thread with no work at that time.

    python benchmarks/tick_floor.py RATE SECONDS [--realtime-priority P]

prints one JSON line: ``held`` [%], ``late_p50_ms``, ``late_p99_ms``.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import threading
import time

import numpy as np


def measure(rate: float, seconds: float) -> dict:
    """Tick at ``rate`` [Hz] for ``seconds`` in a new thread; the share of ticks held and the wake-up lateness."""
    period = 1.0 / rate
    cond = threading.Condition()
    late: list[float] = []
    missed = 0

    def run() -> None:
        nonlocal missed
        due = time.monotonic()
        end = due + seconds
        while due < end:
            with cond:
                now = time.monotonic()
                while now < due:
                    cond.wait(due - now)
                    now = time.monotonic()
            late.append(now - due)
            lost = int((now - due) / period)
            missed += lost
            due += (lost + 1) * period

    thread = threading.Thread(target=run)
    thread.start()
    thread.join()
    lateness = np.array(late)
    return {"held": 100.0 * lateness.size / (lateness.size + missed),
            "late_p50_ms": float(np.median(lateness) * 1e3), "late_p99_ms": float(np.percentile(lateness, 99) * 1e3)}


def floor(rate: float, seconds: float, priority: int = 0) -> dict:
    """:func:`measure` in a fresh process (``priority`` > 0: under ``SCHED_FIFO`` at that priority, as the node)."""
    done = subprocess.run([sys.executable, os.path.abspath(__file__), str(rate), str(seconds),
                           "--realtime-priority", str(priority)], capture_output=True, text=True, check=True)
    return json.loads(done.stdout.strip().splitlines()[-1])


def describe(rate: float, result: dict, priority: int) -> str:
    """One line for a benchmark's output."""
    return (f"machine floor: a bare Python thread ticking at {rate:g} Hz (Condition.wait, as the solver thread; "
            f"realtime_priority {priority}) held {result['held']:.2f} % (woke {result['late_p50_ms']:.3f} ms late "
            f"at the median, {result['late_p99_ms']:.2f} ms at p99)")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("rate", type=float, help="ticks per second")
    parser.add_argument("seconds", type=float)
    parser.add_argument("--realtime-priority", type=int, default=0, help="SCHED_FIFO priority (0: normal)")
    args = parser.parse_args()
    if args.realtime_priority > 0:
        from dea_array_twin.ros.realtime import use_fifo

        use_fifo(args.realtime_priority)
    print(json.dumps(measure(args.rate, args.seconds)))


if __name__ == "__main__":
    main()

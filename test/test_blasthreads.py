"""``single_threaded_blas`` leaves every BLAS product to the thread that calls it."""

import json
import os
import subprocess
import sys

import pytest

#: In a fresh interpreter: pin (or not) the BLAS, then 700 x 700 products until the calling thread has had
#: 0.3 s of CPU (however loaded the machine), and the CPU clock ticks of the calling thread and of every
#: other thread of the process over them (``/proc/self/task/*/stat``: utime + stime, fields 14 and 15).
PROBE = """
import json, os, sys, threading, time
import numpy as np
import scipy.linalg
from dea_array_twin.blasthreads import single_threaded_blas

pinned = single_threaded_blas() if sys.argv[1] == "pin" else None
a = np.random.default_rng(0).random((700, 700))
for _ in range(3):
    a @ a
time.sleep(0.3)  # helper threads that spun after the warm-up have gone to sleep

def ticks():
    out = {}
    for tid in os.listdir("/proc/self/task"):
        with open(f"/proc/self/task/{tid}/stat") as f:
            fields = f.read().rsplit(")", 1)[1].split()
        out[int(tid)] = int(fields[11]) + int(fields[12])
    return out

me, before, start = threading.get_native_id(), ticks(), time.thread_time()
while time.thread_time() - start < 0.3:
    a @ a
after = ticks()
others = sum(n - before.get(t, 0) for t, n in after.items() if t != me)
print(json.dumps({"pinned": pinned, "mine": after[me] - before[me], "others": others}))
"""


def _probe(mode: str) -> dict:
    env = {k: v for k, v in os.environ.items() if not k.endswith("_NUM_THREADS")}  # OpenBLAS's own count
    run = subprocess.run([sys.executable, "-c", PROBE, mode], capture_output=True, text=True, timeout=120, env=env)
    assert run.returncode == 0, run.stderr
    return json.loads(run.stdout)


@pytest.mark.skipif(not os.path.isdir("/proc/self/task"), reason="needs Linux's /proc")
def test_single_threaded_blas_leaves_every_product_to_the_calling_thread():
    """With the wheels' OpenBLAS (numpy's and scipy's), :func:`single_threaded_blas` reports True and the
    other threads of the process get (almost) none of the products' CPU time; without it, on a machine
    with more than one core, OpenBLAS's helper threads take a large share (the probe sees threads).
    Ticks are 10 ms: the calling thread gets ~30."""
    pin = _probe("pin")
    assert pin["pinned"] is True
    assert pin["mine"] >= 20, pin
    assert pin["others"] <= 0.05 * pin["mine"] + 1, pin
    if len(os.sched_getaffinity(0)) > 1:
        free = _probe("free")
        assert free["others"] >= 0.2 * free["mine"], free

"""``warm_up`` compiles the solver's numba kernels up front, so that no update of a live twin compiles.

The node warms its twin up before it says it is ready: a first update that compiles (~10 s after
an install) outlasts the node's stop, and a process that ends with the solver thread still
compiling may exit with code 120 (Python's flush of stdout fails at finalisation).  Checked in a
fresh interpreter, where nothing is compiled or loaded yet: every solve the node makes (checked
and unchecked, driven, free, biased, with voltage, dynamic steps, a path continued through four
states) after ``warm_up`` adds no signature to any kernel (the continuation's among them).
"""

import json
import os
import subprocess
import sys
from pathlib import Path

from conftest import COARSE

SCRIPT = """
import json, sys
import numba
import numpy as np
from dea_array_twin import ArrayConfig, ArrayTwin
from dea_array_twin.model import kernels, ldl, multifrontal, solver

def compiled():
    return {f"{m.__name__}.{name}": len(f.signatures) for m in (kernels, ldl, multifrontal, solver)
            for name, f in vars(m).items() if isinstance(f, numba.core.registry.CPUDispatcher)}

coarse = json.loads(sys.argv[1])
bias = {"type": "linear", "stiffness": 40.0, "free_position": 0.020}
cfg = ArrayConfig(**coarse).replace(unit_modes=("free", "biased", "driven"), bias=(bias,), mass=(0.005,))
twin = ArrayTwin(cfg, background_tangent=True)
fresh = twin._x.copy()
twin.warm_up()
before = compiled()
assert np.array_equal(twin._x, fresh), "warm_up changed the state"
twin.solve(voltage=[0.0, 0.0, 0.0])
twin.solve([0.0, 0.0, 0.004], [1000.0, 1500.0, 0.0], check_stability=True)
twin.solve([0.0, 0.0, 0.0041], check_stability=False)
twin.solve([0.0, 0.005, 0.004], modes=("free", "driven", "driven"), check_stability=False)
twin.solve([0.0, 0.0051, 0.004], modes=("free", "driven", "driven"), check_stability=False)
for d2, d3 in ((0.0052, 0.0041), (0.0053, 0.0043), (0.0054, 0.0046)):  # the cubic continuation
    twin.solve([0.0, d2, d3], modes=("free", "driven", "driven"), check_stability=False)
twin.reset()
for i in range(3):
    twin.step(0.002, [0.0, 0.0, 0.001 * i], [0.0, 800.0, 0.0], force=[0.0, 0.01 * i, 0.0])
twin.close()
print(json.dumps({"before": before, "after": compiled()}))
"""


def test_no_update_compiles_after_warm_up_in_a_fresh_interpreter(tmp_path):
    env = dict(os.environ, PYTHONPATH=str(Path(__file__).resolve().parents[2]))  # this checkout's source
    out = subprocess.run([sys.executable, "-c", SCRIPT, json.dumps(COARSE)], capture_output=True, text=True,
                         timeout=280, cwd=tmp_path, env=env)
    assert out.returncode == 0, out.stderr
    counts = json.loads(out.stdout.strip().splitlines()[-1])
    assert sum(counts["before"].values()) > 0, counts  # warm_up compiled (or loaded) kernels at all
    new = {k: (counts["before"][k], v) for k, v in counts["after"].items() if v != counts["before"][k]}
    assert not new, f"kernels compiled after warm_up (signatures before, after): {new}"

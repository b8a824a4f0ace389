"""Speed of actuator mode against the driven warm update, on the default 1-by-3 array.

Run:  .venv/bin/python benchmarks/bench_actuator.py [CONFIG] [--rounds N] [--updates M] [--before DIR]

Three kinds of update of unit 2 (neighbours free, 0 V, no stability check, as the node
runs), each moving unit 2 by about 0.1 mm, timed in interleaved rounds so that machine
load hits all alike:

  - driven : the indenter commanded +-0.1 mm around 10 mm (bench_core's warm update);
  - biased : unit 2 on an LBS (40 N/m), its external force stepped by +-k_eff * 0.1 mm
             (a quasi-static biased warm update: the height is an unknown);
  - dynamic: the same unit with 5 g, one Newmark step of 2 ms (a 500 Hz node) under a
             force that alternates the same way.

Prints the median and 90th percentile per kind, Newton iterations, residual evaluations,
K_ff solves and factorisations per update (the work, which load does not change), and
the ratios biased/driven and dynamic/driven (target <= ~1.2).  Not a test: numbers for
the notes; note the load (printed) with them.

``--before DIR``: each round runs in a fresh process, alternating between this checkout and
the code in DIR (e.g. a worktree of main before a change: ``git worktree add DIR main``),
both imported through PYTHONPATH (the .venv holds a non-editable install), and the table
shows both, each from its own rounds of the same run.  Figures: docs/actuator.md, "Speed".
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import time

import numpy as np

from dea_array_twin import ArrayTwin, NewtonSettings, load_config
from dea_array_twin.model import solver
from dea_array_twin.model.response import rest_state

#: Residual evaluations and K_ff solves, counted by wrapping the solver's two kernels.
COUNTS = {"residuals": 0, "solves": 0}


def _counting() -> None:
    residual, solve = solver.internal_forces, solver.Factorisation.solve

    def counted_residual(*args):
        COUNTS["residuals"] += 1
        return residual(*args)

    def counted_solve(self, b):
        COUNTS["solves"] += 1
        return solve(self, b)

    solver.internal_forces = counted_residual
    solver.Factorisation.solve = counted_solve

FREE_CENTRE = ("free", "driven", "free")
LBS = {"type": "linear", "stiffness": 40.0, "free_position": 0.020}
STEP = 1e-4  # m per update


def _driven(cfg):
    twin = ArrayTwin(cfg, NewtonSettings(check_stability=False))
    for d in np.linspace(0.0, 0.010, 11):
        twin.solve([0.0, d, 0.0], 0.0, FREE_CENTRE)
    state = {"d": 0.010, "i": 0}

    def update():
        state["d"] += STEP if (state["i"] // 20) % 2 == 0 else -STEP
        state["i"] += 1
        return twin.solve([0.0, state["d"], 0.0], 0.0, FREE_CENTRE)

    return update


def _biased(cfg, mass: float, dt: float | None):
    cfg = cfg.replace(unit_modes=("free", "biased", "free"), bias=(LBS,), mass=(mass,))
    twin = ArrayTwin(cfg, NewtonSettings(check_stability=False))
    rest = rest_state(twin)
    probe = ArrayTwin(cfg.replace(unit_modes=FREE_CENTRE), NewtonSettings(check_stability=False))
    w = rest.position[1]
    stiffness = (probe.solve([0, w + 1e-6, 0]).force[1] - probe.solve([0, w - 1e-6, 0]).force[1]) / 2e-6 + 40.0
    state = {"f": 0.0, "i": 0}

    def update():
        state["f"] += stiffness * STEP if (state["i"] // 20) % 2 == 0 else -stiffness * STEP
        state["i"] += 1
        force = [0.0, state["f"], 0.0]
        return twin.solve(force=force) if dt is None else twin.step(dt, force=force)

    return update


def measure(config: str | None, rounds: int, updates: int) -> dict:
    """Per kind: every update's time [s], Newton iterations, factorisations and height change
    [m], and the residual evaluations and K_ff solves per update; ``rounds`` interleaved."""
    cfg = load_config(config)
    _counting()
    kinds = {"driven": _driven(cfg), "biased": _biased(cfg, 0.0, None), "dynamic": _biased(cfg, 0.005, 0.002)}
    out = {k: {"times": [], "its": [], "facts": [], "moved": [], "residuals": 0, "solves": 0} for k in kinds}
    for _ in range(rounds):
        for name, update in kinds.items():
            last = None
            got = out[name]
            for _ in range(updates):
                before = (COUNTS["residuals"], COUNTS["solves"])
                tic = time.perf_counter()
                res = update()
                got["times"].append(time.perf_counter() - tic)
                got["residuals"] += COUNTS["residuals"] - before[0]
                got["solves"] += COUNTS["solves"] - before[1]
                got["its"].append(res.iterations)
                got["facts"].append(res.factorisations)
                if last is not None:
                    got["moved"].append(abs(res.position[1] - last))
                last = res.position[1]
    return out


def _worker(code_dir: str, args) -> dict:
    """One round in a fresh process importing the package from ``code_dir``."""
    env = dict(os.environ, PYTHONPATH=os.path.abspath(code_dir))
    cmd = [sys.executable, os.path.abspath(__file__), "--worker", "--rounds", "1", "--updates", str(args.updates)]
    cmd += [args.config] if args.config else []
    done = subprocess.run(cmd, env=env, capture_output=True, text=True, check=True, cwd=os.path.abspath(code_dir))
    return json.loads(done.stdout.strip().splitlines()[-1])


def _merge(results: list[dict]) -> dict:
    merged = {}
    for res in results:
        for name, got in res.items():
            into = merged.setdefault(name, {"times": [], "its": [], "facts": [], "moved": [], "residuals": 0,
                                            "solves": 0})
            for key in ("times", "its", "facts", "moved"):
                into[key] += got[key]
            into["residuals"] += got["residuals"]
            into["solves"] += got["solves"]
    return merged


def report(label: str, out: dict) -> None:
    """The table of one version."""
    print(f"{label}:")
    print(f"{'kind':>8}  {'median ms':>9}  {'p90 ms':>7}  {'Newton its':>10}  {'residuals':>9}  {'solves':>6}  "
          f"{'facts':>6}  {'mean |dw| mm':>12}")
    for name, got in out.items():
        n = len(got["times"])
        print(f"{name:>8}  {1e3 * statistics.median(got['times']):9.2f}  "
              f"{1e3 * float(np.percentile(got['times'], 90)):7.2f}  {np.mean(got['its']):10.2f}  "
              f"{got['residuals'] / n:9.2f}  {got['solves'] / n:6.2f}  {np.mean(got['facts']):6.3f}  "
              f"{1e3 * np.mean(got['moved']):12.4f}")
    base = statistics.median(out["driven"]["times"])
    print(f"biased/driven: {statistics.median(out['biased']['times']) / base:.2f}   "
          f"dynamic/driven: {statistics.median(out['dynamic']['times']) / base:.2f}   (target <= ~1.2)")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("config", nargs="?", help="config YAML (default: the paper's 1-by-3 array)")
    parser.add_argument("--rounds", type=int, default=5, help="interleaved rounds (default 5)")
    parser.add_argument("--updates", type=int, default=40, help="updates per kind and round (default 40)")
    parser.add_argument("--before", metavar="DIR", help="also measure the code in DIR, alternating rounds")
    parser.add_argument("--worker", action="store_true", help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.worker:
        print(json.dumps(measure(args.config, args.rounds, args.updates)))
        return
    print(f"load before: {os.getloadavg()[0]:.2f} (1-min average, {os.cpu_count()} cores)")
    if not args.before:
        out = measure(args.config, args.rounds, args.updates)
        print(f"load after: {os.getloadavg()[0]:.2f}")
        report("this checkout", out)
        return
    here = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
    versions = [("after", here), ("before", args.before)]
    rounds: dict[str, list[dict]] = {name: [] for name, _ in versions}
    for r in range(args.rounds):
        for name, code in (versions if r % 2 == 0 else versions[::-1]):
            rounds[name].append(_worker(code, args))
            print(f"  round {r + 1} {name} done (load {os.getloadavg()[0]:.2f})", flush=True)
    print(f"load after: {os.getloadavg()[0]:.2f}")
    report(f"before ({os.path.abspath(args.before)})", _merge(rounds["before"]))
    report(f"after ({here})", _merge(rounds["after"]))


if __name__ == "__main__":
    main()

"""Speed of actuator mode against the driven warm update, on the default 1-by-3 array.

Run:  .venv/bin/python benchmarks/bench_actuator.py [CONFIG] [--rounds N] [--updates M]

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
"""

from __future__ import annotations

import argparse
import os
import statistics
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


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("config", nargs="?", help="config YAML (default: the paper's 1-by-3 array)")
    parser.add_argument("--rounds", type=int, default=5, help="interleaved rounds (default 5)")
    parser.add_argument("--updates", type=int, default=40, help="updates per kind and round (default 40)")
    args = parser.parse_args()
    cfg = load_config(args.config)
    _counting()
    print(f"load before: {os.getloadavg()[0]:.2f} (1-min average, {os.cpu_count()} cores)")
    kinds = {"driven": _driven(cfg), "biased": _biased(cfg, 0.0, None), "dynamic": _biased(cfg, 0.005, 0.002)}
    times = {k: [] for k in kinds}
    its = {k: [] for k in kinds}
    facts = {k: [] for k in kinds}
    moved = {k: [] for k in kinds}
    work = {k: np.zeros(2) for k in kinds}
    for _ in range(args.rounds):
        for name, update in kinds.items():
            last = None
            for _ in range(args.updates):
                before = np.array([COUNTS["residuals"], COUNTS["solves"]])
                tic = time.perf_counter()
                res = update()
                times[name].append(time.perf_counter() - tic)
                work[name] += np.array([COUNTS["residuals"], COUNTS["solves"]]) - before
                its[name].append(res.iterations)
                facts[name].append(res.factorisations)
                if last is not None:
                    moved[name].append(abs(res.position[1] - last))
                last = res.position[1]
    print(f"load after: {os.getloadavg()[0]:.2f}")
    print(f"{'kind':>8}  {'median ms':>9}  {'p90 ms':>7}  {'Newton its':>10}  {'residuals':>9}  {'solves':>6}  "
          f"{'facts':>6}  {'mean |dw| mm':>12}")
    for name in kinds:
        residuals, solves = work[name] / len(times[name])
        print(f"{name:>8}  {1e3 * statistics.median(times[name]):9.2f}  "
              f"{1e3 * float(np.percentile(times[name], 90)):7.2f}  {np.mean(its[name]):10.2f}  {residuals:9.2f}  "
              f"{solves:6.2f}  {np.mean(facts[name]):6.3f}  {1e3 * np.mean(moved[name]):12.4f}")
    base = statistics.median(times["driven"])
    print(f"biased/driven: {statistics.median(times['biased']) / base:.2f}   "
          f"dynamic/driven: {statistics.median(times['dynamic']) / base:.2f}   (target <= ~1.2)")


if __name__ == "__main__":
    main()

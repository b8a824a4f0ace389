"""Speed of the studies and of calibration on the default 1-by-3 array (paper, Table 1).

Run:  .venv/bin/python benchmarks/bench_studies.py [CONFIG] [--steps N] [--workers N]

Reports:
  - s for the five curves of one set of coupling indices (eqs. 13-16), run here, and on
    ``--workers`` spawned processes (process start-up and meshing included);
  - s per calibration cost evaluation: one 16-point force curve re-solved with new
    Yeoh coefficients (what Nelder-Mead pays per trial point).
Not a test: numbers for the notes.
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from dea_array_twin import ArrayTwin, load_config
from dea_array_twin.calibration import MeasuredCurve, simulate
from dea_array_twin.studies import coupling_indices, coupling_tasks, run_curve, run_tasks


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("config", nargs="?")
    parser.add_argument("--steps", type=int, default=15)
    parser.add_argument("--workers", type=int, default=2)
    args = parser.parse_args()
    cfg = load_config(args.config)
    tasks = coupling_tasks(cfg, args.steps)
    ArrayTwin(cfg)  # mesh once in this process, outside the timings
    for workers in (1, args.workers):
        tic = time.perf_counter()
        curves = run_tasks(run_curve, tasks, workers=workers)
        elapsed = time.perf_counter() - tic
        ci = coupling_indices({c.task.key[-1]: c for c in curves})
        print(f"coupling indices, {len(tasks)} curves x {args.steps + 1} points, {workers} worker(s): "
              f"{elapsed:.2f} s  (eta_F,LV {ci.eta_f_lv:.3f} %, eta_F,HV {ci.eta_f_hv:.3f} %, eta_C {ci.eta_c:.3f} %)")
    d = np.zeros((16, cfg.n_units))
    d[:, 1] = np.linspace(0.0, 0.015, 16)
    curve = MeasuredCurve("bench", cfg, ("free", "driven", "free"), d, np.zeros_like(d), 1, force=np.ones(16))
    times = []
    for c10 in np.linspace(0.15e6, 0.21e6, 5):
        tic = time.perf_counter()
        simulate(ArrayTwin(cfg.replace(c10=c10)), curve)
        times.append(time.perf_counter() - tic)
    print(f"calibration cost evaluation (16-point curve, new coefficients): median {np.median(times):.3f} s")


if __name__ == "__main__":
    main()

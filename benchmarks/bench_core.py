"""Speed of the membrane core on the default 1-by-3 array (paper, Table 1).

Run:  .venv/bin/python benchmarks/bench_core.py [CONFIG] [--repeat N]

Reports, for the default mesh and for each stability-check setting:
  - ms per warm update: unit 2 stepped by 0.1 mm around 10 mm, neighbours free (median);
  - ms per cold solve: a fresh twin (mesh cached) straight to d2 = 15 mm;
  - s per 0-15 mm curve of 16 points (unit 2, neighbours free, V = 0);
with dofs, Newton iterations and factorisations.  Not a test: numbers for the notes.
"""

from __future__ import annotations

import argparse
import statistics
import time

import numpy as np

from dea_array_twin import ArrayTwin, NewtonSettings, load_config

MODES = ("free", "driven", "free")


def _command(twin: ArrayTwin, d: float) -> np.ndarray:
    cmd = np.zeros(twin.n_units)
    cmd[1] = d
    return cmd


def bench(cfg, check_stability: bool, repeat: int) -> dict:
    settings = NewtonSettings(check_stability=check_stability)
    ArrayTwin(cfg)  # mesh once (cached), outside the timings
    curve_times, curve_iters = [], []
    for _ in range(repeat):
        twin = ArrayTwin(cfg, settings)
        tic = time.perf_counter()
        iters = 0
        for d in np.linspace(0.0, 0.015, 16):
            iters += twin.solve(_command(twin, d), 0.0, MODES).iterations
        curve_times.append(time.perf_counter() - tic)
        curve_iters.append(iters)
    cold = []
    for _ in range(repeat):
        twin = ArrayTwin(cfg, settings)
        tic = time.perf_counter()
        res = twin.solve(_command(twin, 0.015), 0.0, MODES)
        cold.append((time.perf_counter() - tic, res.iterations, res.factorisations))
    twin = ArrayTwin(cfg, settings)
    for d in np.linspace(0.0, 0.010, 11):
        twin.solve(_command(twin, d), 0.0, MODES)
    warm, warm_iters, warm_facts = [], [], []
    d = 0.010
    for i in range(100 * repeat):
        d += 1e-4 if (i // 20) % 2 == 0 else -1e-4
        tic = time.perf_counter()
        res = twin.solve(_command(twin, d), 0.0, MODES)
        warm.append(time.perf_counter() - tic)
        warm_iters.append(res.iterations)
        warm_facts.append(res.factorisations)
    return {
        "dofs": twin.model.disc.n_dofs,
        "elements": twin.model.mesh.n_elements,
        "warm_ms": 1e3 * statistics.median(warm),
        "warm_p90_ms": 1e3 * float(np.percentile(warm, 90)),
        "warm_iterations": float(np.mean(warm_iters)),
        "warm_factorisations": float(np.mean(warm_facts)),
        "cold_ms": 1e3 * min(c[0] for c in cold),
        "cold_iterations": cold[0][1],
        "cold_factorisations": cold[0][2],
        "curve_s": min(curve_times),
        "curve_iterations": curve_iters[0],
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("config", nargs="?", help="config YAML (default: the paper's 1-by-3 array)")
    parser.add_argument("--repeat", type=int, default=3)
    args = parser.parse_args()
    cfg = load_config(args.config)
    print(f"mesh: order {cfg.element_order}, sizes {cfg.mesh_size * 1e3:g}/{cfg.mesh_size_electrode * 1e3:g}/"
          f"{cfg.mesh_size_indenter * 1e3:g} mm (far/electrode/indenter)")
    for check in (True, False):
        r = bench(cfg, check, args.repeat)
        print(f"check_stability={check}: {r['elements']} elements, {r['dofs']} dofs")
        print(f"  warm update : {r['warm_ms']:.2f} ms median, {r['warm_p90_ms']:.2f} ms p90 "
              f"({r['warm_iterations']:.1f} Newton its, {r['warm_factorisations']:.2f} factorisations per update)")
        print(f"  cold solve  : {r['cold_ms']:.0f} ms to 15 mm ({r['cold_iterations']} its, "
              f"{r['cold_factorisations']} factorisations)")
        print(f"  16-pt curve : {r['curve_s']:.3f} s ({r['curve_iterations']} Newton its)")


if __name__ == "__main__":
    main()

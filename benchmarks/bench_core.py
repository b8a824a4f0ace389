"""Speed of the membrane core against the targets of issue 16, with accuracy beside each timing.

Run:
  .venv/bin/python benchmarks/bench_core.py [CONFIG] [--rounds N] [--before DIR]
  .venv/bin/python benchmarks/bench_core.py --arrays [--sizes 1x3,2x2,3x3,4x4,8x8] [--refine 1.5,2,3] [--before DIR]
  .venv/bin/python benchmarks/bench_core.py --node SECONDS [--rounds N] [--before DIR]

Default: the 1-by-3 array (CONFIG, default the paper's Table 1 and mesh), unit 2
driven, its neighbours free, V = 0:
  - warm update: unit 2 stepped by 0.1 mm between 10 and 12 mm, no stability check
    (median, p90 of 100 per round);
  - checked update: the same with the stability check at every update (median of 40);
  - 16-point curve 0-15 mm, unchecked and checked at every point;
  - cold solve: a fresh twin (mesh cached) straight from 0 to 15 mm;
each with dofs, Newton iterations and factorisations, the figure before (the issue's
numbers) and the force error against a reference on a mesh with every size / 3
(about 9x the elements).  Each round runs in a fresh process; ``--before DIR`` also
runs the same measurements on the code in DIR (e.g. a worktree of the old main),
alternating with this checkout round by round, so both see the same machine load.

``--arrays``: the scaling table, centre unit driven, the others free: rows x cols
grids with square frames of n D + (n - 1) d + 2 b (155 mm for 4x4, 295 mm for 8x8),
default mesh sizes, plus the 1-by-3 with every mesh size divided by the --refine
factors; dofs, mesh time, first solve to 5 mm, warm (0.1 mm) and checked update
medians, and the growth exponent of time against dofs; with ``--before DIR`` each row
is measured in fresh processes on this checkout and on DIR, alternating, and DIR's
warm/checked medians and first solve are printed beside.

``--node``: the twin node in its own process at ``update_rate: 500`` with a smooth
command stream (a 1 Hz sine on each unit, sent at 500 Hz), stability checks at the
default period, the node's ``realtime_priority`` at ``--realtime-priority`` (0: normal
scheduling); the share of ticks it publishes outputs for (goal >= 99 %), the CPU the node
process used (cores) and its diagnostics; with ``--before DIR`` alternating with the code in
DIR, a fresh node process per round; before and after the rounds, the machine's floor
(``tick_floor.py``: a bare Python thread ticking at the same rate and scheduling).

Not a test: numbers for the notes.  The load (``os.getloadavg``) is printed with them.
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

# The "before" figures (main at cba35fa on this 2-core machine), and its targets.
TARGETS = {  # key: (label, unit, before, target)
    "warm": ("warm update, 0.1 mm, unchecked", "ms", "4-10 (2.3-5 its)", 2.0),
    "checked": ("checked update, 0.1 mm", "ms", "30-60", 8.0),
    "curve": ("16-point curve 0-15 mm, unchecked", "s", "0.43 [a]", 0.1),
    "curve_checked": ("16-point curve, checked at every point", "s", "0.84 [a]", 0.25),
    "cold": ("cold solve 0 -> 15 mm", "ms", "1000-2000 (31 facts)", 250.0),
}
NODE_RATE = 500.0  # update_rate and command rate of --node [Hz]
ARRAY_TARGETS = {"4x4": (10.0, 50.0, None), "8x8": (50.0, 250.0, 3.0)}  # warm ms, checked ms, first solve s
ARRAY_BEFORE = {"1x3": "4-10/30-60", "2x2": "7.7/66", "3x3": "24.7/166", "4x4": "36.5/294",
                "8x8": "94-1420/1200+ (first 5 mm: 24 s incl. mesh)"}


def _load() -> str:
    return "load %.2f %.2f %.2f" % os.getloadavg()


def _twin(cfg, check: bool):
    from dea_array_twin import ArrayTwin, NewtonSettings

    return ArrayTwin(cfg, NewtonSettings(check_stability=check))


def _centre(cfg) -> int:
    return (cfg.rows // 2) * cfg.cols + cfg.cols // 2 if cfg.layout == "array" else 0


def _command(cfg, d: float) -> tuple[np.ndarray, tuple[str, ...]]:
    n, k = cfg.n_units, _centre(cfg)
    cmd = np.zeros(n)
    cmd[k] = d
    return cmd, tuple("driven" if i == k else "free" for i in range(n))


def _updates(twin, cfg, count: int, start: float, check: bool) -> tuple[list, list, list, float, float]:
    """``count`` 0.1 mm updates from ``start`` (20 up, 20 down, ...): times, its, facts, last d, last F."""
    times, its, facts = [], [], []
    d = start
    for i in range(count):
        d += 1e-4 if (i // 20) % 2 == 0 else -1e-4
        cmd, modes = _command(cfg, d)
        tic = time.perf_counter()
        res = twin.solve(cmd, 0.0, modes, check_stability=check)
        times.append(time.perf_counter() - tic)
        its.append(res.iterations)
        facts.append(res.factorisations)
    return times, its, facts, d, float(res.force[_centre(cfg)])


def _warm_up(cfg) -> None:
    """Mesh (cached), compiled code and symbolic analysis loaded, outside the timings.

    ``ArrayTwin.warm_up`` loads every kernel an update may call (what a live twin does
    before its first update; without it the first 16-point curve of a process took
    ~15 ms more, loading the continuation's kernels), then a checked step with the
    measured unit modes loads their symbolic analysis."""
    twin = _twin(cfg, True)
    twin.warm_up()
    cmd, modes = _command(cfg, 1e-4)
    twin.solve(cmd, 0.0, modes)


def measure_row(cfg) -> dict:
    """One round of the 1-by-3 measurements (runs in a worker process)."""
    k = _centre(cfg)
    _warm_up(cfg)
    out = {"dofs": 0, "n_free": 0}
    for key, check in (("curve", False), ("curve_checked", True)):
        twin = _twin(cfg, check)
        tic = time.perf_counter()
        its, forces = 0, []
        for d in np.linspace(0.0, 0.015, 16):
            cmd, modes = _command(cfg, d)
            res = twin.solve(cmd, 0.0, modes)
            its += res.iterations
            forces.append(float(res.force[k]))
        out[key] = {"value": time.perf_counter() - tic, "its": its, "forces": forces,
                    "facts": None, "d": np.linspace(0.0, 0.015, 16).tolist()}
        out["dofs"] = twin.model.disc.n_dofs
    twin = _twin(cfg, False)
    cmd, modes = _command(cfg, 0.015)
    tic = time.perf_counter()
    res = twin.solve(cmd, 0.0, modes)
    out["cold"] = {"value": 1e3 * (time.perf_counter() - tic), "its": res.iterations, "facts": res.factorisations,
                   "forces": [float(res.force[k])], "d": [0.015]}
    for key, check, count in (("warm", False, 100), ("checked", True, 40)):
        twin = _twin(cfg, False)
        for d in np.linspace(0.0, 0.010, 11):
            cmd, modes = _command(cfg, d)
            twin.solve(cmd, 0.0, modes)
        times, its, facts, d, force = _updates(twin, cfg, count, 0.010, check)
        out[key] = {"value": 1e3 * statistics.median(times), "p90": 1e3 * float(np.percentile(times, 90)),
                    "its": float(np.mean(its)), "facts": float(np.mean(facts)), "forces": [force], "d": [d]}
    return out


def reference_forces(cfg, points: list[float], factor: float = 3.0) -> dict[float, float]:
    """Force on the driven unit at each displacement on a mesh with every size / ``factor``."""
    fine = cfg.replace(mesh_size=cfg.mesh_size / factor, mesh_size_indenter=cfg.mesh_size_indenter / factor,
                       mesh_size_electrode=cfg.mesh_size_electrode / factor)
    twin = _twin(fine, False)
    out = {}
    for d in sorted(set(points)):
        cmd, modes = _command(fine, d)
        out[d] = float(twin.solve(cmd, 0.0, modes).force[_centre(fine)])
    return out


def _run_worker(code_dir: str | None, config: str | None) -> dict:
    env = dict(os.environ)
    if code_dir:
        env["PYTHONPATH"] = os.path.abspath(code_dir)
    cmd = [sys.executable, __file__, "--worker"] + ([config] if config else [])
    done = subprocess.run(cmd, env=env, capture_output=True, text=True, check=True)
    return json.loads(done.stdout.strip().splitlines()[-1])


def _error(entry: dict, ref: dict[float, float]) -> float:
    """Largest relative force error [%] of a measurement against the reference."""
    return max(100.0 * abs(f - ref[round(d, 7)]) / abs(ref[round(d, 7)])
               for f, d in zip(entry["forces"], entry["d"]) if d > 0)


def main_row(args) -> None:
    from dea_array_twin import load_config

    cfg = load_config(args.config)
    here = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))  # this checkout, not the install
    versions = [("after", here)] + ([("before", args.before)] if args.before else [])
    print(f"1-by-3 targets; {_load()} at start; {args.rounds} round(s) per version, each a fresh process")
    rounds: dict[str, list[dict]] = {name: [] for name, _ in versions}
    for r in range(args.rounds):
        for name, code in (versions if r % 2 == 0 else versions[::-1]):
            rounds[name].append(_run_worker(code, args.config))
            print(f"  round {r + 1} {name} done ({_load()})", flush=True)
    points = [round(d, 7) for res in rounds["after"] for key in TARGETS for d in res[key]["d"] if d > 0]
    ref = {round(d, 7): f for d, f in reference_forces(cfg, points).items()}
    after = rounds["after"][0]
    print(f"mesh: order {cfg.element_order}, sizes {cfg.mesh_size * 1e3:g}/{cfg.mesh_size_electrode * 1e3:g}/"
          f"{cfg.mesh_size_indenter * 1e3:g} mm (far/electrode/indenter), {after['dofs']} dofs; "
          f"force error against every size / 3")
    head = f"{'target':40s} {'unit':>4s} {'issue before':>22s} " + (
        f"{'measured before':>16s} " if args.before else "") + f"{'after':>9s} {'goal':>7s} {'its':>6s} " \
        f"{'facts':>6s} {'F error %':>9s}"
    print(head)
    for key, (label, unit, before, target) in TARGETS.items():
        med = {name: statistics.median(res[key]["value"] for res in rounds[name]) for name in rounds}
        last = rounds["after"][-1][key]
        facts = "-" if last["facts"] is None else f"{last['facts']:.2f}".rstrip("0").rstrip(".")
        its = f"{last['its']:.1f}" if isinstance(last["its"], float) else str(last["its"])
        fmt = "{:.3f}" if unit == "s" else "{:.2f}"
        line = f"{label:40s} {unit:>4s} {before:>22s} "
        if args.before:
            line += f"{fmt.format(med['before']):>16s} "
        line += (f"{fmt.format(med['after']):>9s} {'<= ' + format(target, 'g'):>7s} {its:>6s} {facts:>6s} "
                 f"{_error(last, ref):9.4f}")
        print(line)
    warm = [res["warm"] for res in rounds["after"]]
    print(f"warm update p90: {statistics.median(w['p90'] for w in warm):.2f} ms; checked update p90: "
          f"{statistics.median(res['checked']['p90'] for res in rounds['after']):.2f} ms")
    print("[a] not in the issue: the benchmark of main at cba35fa on this machine (load ~1.5)")
    print(f"{_load()} at the end")


# ----------------------------------------------------------------------------- scaling
def _grid(rows: int, cols: int):
    from dea_array_twin import ArrayConfig

    base = ArrayConfig()
    b = 0.015  # electrode-to-frame distance of Table 1
    size = lambda n: n * base.electrode_diameter + (n - 1) * base.spacing + 2 * b  # noqa: E731
    return base.replace(rows=rows, cols=cols, length=size(cols), width=size(rows))


def measure_array(cfg, warm_count: int, checked_count: int) -> dict:
    from dea_array_twin.model.mesh import build_mesh

    tic = time.perf_counter()
    build_mesh(cfg)
    mesh_s = time.perf_counter() - tic
    _warm_up(cfg.replace(layout="circular"))  # compiled code loaded, outside the timings
    twin = _twin(cfg, False)
    cmd, modes = _command(cfg, 0.005)
    tic = time.perf_counter()
    res = twin.solve(cmd, 0.0, modes)
    first = (time.perf_counter() - tic, res.iterations, res.factorisations)
    warm = _updates(twin, cfg, warm_count, 0.005, False)
    checked = _updates(twin, cfg, checked_count, warm[3], True)
    return {"dofs": twin.model.disc.n_dofs, "mesh_s": mesh_s, "first": first,
            "warm_ms": 1e3 * statistics.median(warm[0]), "warm_its": float(np.mean(warm[1])),
            "warm_facts": float(np.mean(warm[2])),
            "checked_ms": 1e3 * statistics.median(checked[0]), "checked_its": float(np.mean(checked[1]))}


def _array_rows(sizes: str, refine: str) -> list[tuple[str, object]]:
    """(name, config) of the scaling rows: the grids, then the 1-by-3 refined by each factor."""
    from dea_array_twin import ArrayConfig

    rows = []
    for size in sizes.split(","):
        r, c = (int(v) for v in size.split("x"))
        rows.append((size, _grid(r, c) if (r, c) != (1, 3) else ArrayConfig()))
    base = ArrayConfig()
    for f in (float(v) for v in refine.split(",") if v):
        refined = base.replace(mesh_size=base.mesh_size / f, mesh_size_electrode=base.mesh_size_electrode / f,
                               mesh_size_indenter=base.mesh_size_indenter / f)
        rows.append((f"1x3 /{f:g}", refined))
    return rows


def _measure_row_of(name: str, cfg) -> dict:
    big = cfg.n_units >= 36
    return measure_array(cfg, 10 if big else 40, 5 if big else 20)


def _run_array_worker(code_dir: str, name: str, refine: str) -> dict:
    """One scaling row measured in a fresh process on the code in ``code_dir``."""
    env = dict(os.environ, PYTHONPATH=os.path.abspath(code_dir))
    sizes = name if "/" not in name else "1x3"
    cmd = [sys.executable, __file__, "--worker-array", name, "--sizes", sizes, "--refine", refine]
    done = subprocess.run(cmd, env=env, capture_output=True, text=True, check=True)
    return json.loads(done.stdout.strip().splitlines()[-1])


def main_arrays(args) -> None:
    rows = _array_rows(args.sizes, args.refine)
    here = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
    print(f"scaling: centre unit driven to 5 mm, others free; {_load()} at start"
          + (f"; each row in fresh processes, this checkout and {args.before} alternating" if args.before else ""))
    print(f"{'array':10s} {'frame mm':>10s} {'dofs':>7s} {'mesh s':>7s} {'first s (its/facts)':>20s} "
          f"{'warm ms (its, facts)':>22s} {'checked ms':>10s} "
          + (f"{'before w/c ms/first s':>22s} " if args.before else "")
          + f"{'goal w/c/first':>16s} {'issue before w/c ms':>22s}")
    dofs, warm, checked = [], [], []
    for i, (name, cfg) in enumerate(rows):
        if args.before:
            refine = name.split("/")[1] if "/" in name else ""
            versions = [("after", here), ("before", args.before)]
            got = {v: _run_array_worker(code, name, refine) for v, code in (versions if i % 2 == 0 else versions[::-1])}
            m, old = got["after"], got["before"]
            before = f"{old['warm_ms']:.2f}/{old['checked_ms']:.1f}/{old['first'][0]:.2f}"
        else:
            m, before = _measure_row_of(name, cfg), None
        goal = ARRAY_TARGETS.get(name)
        goal_s = "/".join("-" if g is None else f"{g:g}" for g in goal) if goal else ""
        first = f"{m['first'][0]:.2f} ({m['first'][1]}/{m['first'][2]})"
        print(f"{name:10s} {cfg.length * 1e3:4.0f}x{cfg.width * 1e3:<5.0f} {m['dofs']:7d} {m['mesh_s']:7.2f} "
              f"{first:>20s} {m['warm_ms']:8.2f} ({m['warm_its']:.1f}, {m['warm_facts']:.2f}) "
              f"{m['checked_ms']:10.1f} " + (f"{before:>22s} " if before else "")
              + f"{goal_s:>16s} {ARRAY_BEFORE.get(name, ''):>22s}", flush=True)
        dofs.append(m["dofs"])
        warm.append(m["warm_ms"])
        checked.append(m["checked_ms"])
    if len(dofs) > 2:
        slope_w = np.polyfit(np.log(dofs), np.log(warm), 1)[0]
        slope_c = np.polyfit(np.log(dofs), np.log(checked), 1)[0]
        print(f"growth: warm ~ dofs^{slope_w:.2f}, checked ~ dofs^{slope_c:.2f} (least squares over all rows); "
              f"{_load()} at the end")


# ----------------------------------------------------------------------------- node
def _cpu_seconds(pid: int) -> float:
    """User + system CPU time [s] of process ``pid`` so far (Linux /proc)."""
    with open(f"/proc/{pid}/stat") as f:
        fields = f.read().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def measure_node(seconds: float, priority: int = 0) -> dict:
    """The twin node (its own process) at update_rate 500 on a 1 Hz sine command on each unit, sent from
    this process at 500 Hz: the share of ticks with a force message, the node's CPU and its diagnostics."""
    import math

    from dea_array_twin.ros.testing import TwinHarness

    rate = NODE_RATE
    params = {"update_rate": rate, "marker_rate": 0.0, "realtime_priority": priority}
    if priority > 0:  # the sender real-time too, as a real-time rig runs its controller
        try:
            from dea_array_twin.ros.realtime import use_fifo
        except ImportError:  # --before code without realtime_priority: its node ignores it, the sender too
            pass
        else:
            use_fifo(priority)
    with TwinHarness(parameters=params, process=True) as h:
        start = tick = time.monotonic()
        window = cpu = None
        while time.monotonic() - start < seconds + 2.0:
            t = time.monotonic() - start
            h.send_displacement([0.005 + 0.004 * math.sin(2 * math.pi * (t + k / 3.0)) for k in range(3)])
            if window is None and t >= 2.0:
                h.clear()
                window, cpu = time.monotonic(), _cpu_seconds(h.process.pid)
            tick += 1.0 / rate
            time.sleep(max(0.0, tick - time.monotonic()))
        elapsed = time.monotonic() - window
        cpu = (_cpu_seconds(h.process.pid) - cpu) / elapsed
        forces = len(h.messages("force"))
        diags = h.messages("/diagnostics")
    values = {kv.key: kv.value for kv in diags[-1].status[0].values} if diags else {}
    return {"held": 100.0 * forces / (rate * elapsed), "outputs_per_s": forces / elapsed, "node_cpu": cpu,
            "solve_ms_p50": float(values.get("solve_time_p50_ms", "nan")),
            "iterations": values.get("iterations"), "updates": values.get("updates"),
            "skipped_ticks": values.get("skipped_ticks"),
            "background_tangents": values.get("background_tangents_installed", "-"), "load": os.getloadavg()[0]}


def main_node(args) -> None:
    """The node benchmark, --rounds fresh node processes per version, alternating with --before."""
    from tick_floor import describe, floor

    here = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))  # this checkout, not the install
    versions = [("after", here)] + ([("before", os.path.abspath(args.before))] if args.before else [])
    print(f"node: update_rate {NODE_RATE:g} Hz, commands at {NODE_RATE:g} Hz from another process: unit k at "
          f"5 + 4 sin(2 pi t + 2 pi k / 3) mm, stability_check_period 1 s (default), "
          f"realtime_priority {args.realtime_priority}; {args.node:g} s measured "
          f"after 2 s; {args.rounds} round(s) per version; {_load()} at start")
    print(describe(NODE_RATE, floor(NODE_RATE, args.node, args.realtime_priority), args.realtime_priority))
    print(f"{'round':>5s} {'version':>7s} {'ticks held':>10s} {'outputs/s':>9s} {'node CPU':>8s} "
          f"{'solve p50 ms':>12s} {'its':>4s} {'updates':>7s} {'skipped':>7s} {'bg tangents':>11s} {'load':>5s}")
    held: dict[str, list[float]] = {name: [] for name, _ in versions}
    for r in range(args.rounds):
        for name, code in (versions if r % 2 == 0 else versions[::-1]):
            env = dict(os.environ, PYTHONPATH=code)  # the node process (python -m) imports from its cwd first
            done = subprocess.run([sys.executable, os.path.abspath(__file__), "--node-worker", str(args.node),
                                   "--realtime-priority", str(args.realtime_priority)],
                                  cwd=code, env=env, capture_output=True, text=True, check=True)
            m = json.loads(done.stdout.strip().splitlines()[-1])
            held[name].append(m["held"])
            print(f"{r + 1:5d} {name:>7s} {m['held']:9.1f}% {m['outputs_per_s']:9.1f} {m['node_cpu']:8.2f} "
                  f"{m['solve_ms_p50']:12.2f} {str(m['iterations']):>4s} {str(m['updates']):>7s} "
                  f"{str(m['skipped_ticks']):>7s} {str(m['background_tangents']):>11s} {m['load']:5.2f}", flush=True)
    for name, values in held.items():
        print(f"{name}: ticks held, median of {len(values)}: {statistics.median(values):.1f} % (goal >= 99 %)")
    print(f"node CPU: cores the node process used (executor, solver and tangent threads); {_load()} at the end")
    print(describe(NODE_RATE, floor(NODE_RATE, args.node, args.realtime_priority), args.realtime_priority)
          + " (after)")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0], epilog=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("config", nargs="?", help="config YAML (default: the paper's 1-by-3 array)")
    parser.add_argument("--rounds", type=int, default=3, help="fresh processes per version (default 3)")
    parser.add_argument("--before", metavar="DIR", help="also measure the code in DIR, interleaved")
    parser.add_argument("--arrays", action="store_true", help="the scaling table instead")
    parser.add_argument("--sizes", default="1x3,2x2,3x3,4x4,8x8", help="grids for --arrays")
    parser.add_argument("--refine", default="1.5,2,3", help="mesh refinement factors of the 1x3 for --arrays")
    parser.add_argument("--node", type=float, metavar="SECONDS",
                        help="measure the twin node at update_rate 500 on a sine command for SECONDS instead")
    parser.add_argument("--worker", action="store_true", help=argparse.SUPPRESS)
    parser.add_argument("--worker-array", help=argparse.SUPPRESS)
    parser.add_argument("--realtime-priority", type=int, default=0,
                        help="--node: the node's realtime_priority (SCHED_FIFO; default 0, normal scheduling)")
    parser.add_argument("--node-worker", type=float, help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.worker:
        from dea_array_twin import load_config

        print(json.dumps(measure_row(load_config(args.config))))
    elif args.worker_array:
        cfg = dict(_array_rows(args.sizes, args.refine))[args.worker_array]
        print(json.dumps(_measure_row_of(args.worker_array, cfg)))
    elif args.node_worker:
        print(json.dumps(measure_node(args.node_worker, args.realtime_priority)))
    elif args.arrays:
        main_arrays(args)
    elif args.node:
        main_node(args)
    else:
        main_row(args)


if __name__ == "__main__":
    main()

"""The reduced twin against its targets: accuracy on held-out commands and warm trajectories, time per update.

Run:  .venv/bin/python benchmarks/bench_rom.py [--size 1x3|4x4] [--snapshots N] [--modes R]
                                               [--validation N] [--workers N] [--rom FILE] [--save FILE]
                                               [--pace HZ] [--second-step S] [--against FILE ...]
                                               [--threaded-blas] [--revalidate N]
      .venv/bin/python benchmarks/bench_rom.py --rom FILE --node SECONDS [--fe-check-rate HZ]
                                               [--realtime-priority P]

Reports (default mesh, every unit driven, d in [0, 0.75 D], V in [0, eq. 14 voltage]):
  - training cost: FE snapshots (wall and CPU s), basis + hyper-reduction, sizes;
  - the error table over ``--validation`` held-out commands (FE as the truth): force error
    over each unit's largest |F|, capacitance error over C, max and mean;
  - warm trajectories (a random walk of every indenter by ``--step`` per update and every
    voltage by the matching fraction of its range, reflected at the envelope): the same
    errors against FE warm solves (and the FE's time per warm update), then the time per
    update of the library's ``ReducedTwin.solve`` running alone on the same paths
    (median, mean, p99, max; refreshes in the calling thread, then ``background_refresh``
    with the Hessians as BLAS products, the process's BLAS on one thread as in the node;
    ``--threaded-blas`` leaves OpenBLAS its threads and the worker's Hessians per point;
    back to back, or one per period at ``--pace`` Hz, as a control loop runs them), with the
    errors of the timed updates themselves (with ``background_refresh`` they depend on how far
    the worker lags, which the FE's solves between the updates above would hide);
  - the same for actuator units (``--kinds``): ``biased``, the middle unit biased on an
    LBS of 40 N/m (free position 10.75 mm) with a force command of 20 mN sin(2 pi i / 200)
    at update i, the other units on the paths (quasi-static solves); ``dynamic``, the same
    with a moving mass of 5 g, one ``ReducedTwin.step`` of 1 ms per update; errors (also of
    the biased height) against the FE twin's solves / steps on the same commands, then the
    kinds' timings interleaved in ``--rounds`` rounds (noise on a shared machine);
``--node SECONDS``: instead, the twin node (its own process) with ``model: rom`` and the
ROM of ``--rom`` at ``update_rate: 1000``, commands at 1 kHz (unit k at 7.5 + 5 sin(2 pi t
+ 2 pi k / n) mm, 1000 V on every unit), the FE check at ``--fe-check-rate``, the node's
``realtime_priority`` at ``--realtime-priority`` (0: normal scheduling), with the machine's
floor before and after it (``tick_floor.py``: a bare thread at the same rate); reports
the force messages per tick (every tick publishes), the node's diagnostics and the CPU the node process
and this one used.
Targets (issue 15): 1x3 <= 0.1 % force and capacitance error, <= 0.1 ms per update,
the node at 1 kHz holding >= 99 % of its ticks; 4x4 <= 0.5 ms per update.
``--second-step X`` runs the paths with ``ReducedTwin(..., second_step=X)`` (the output change of
a first correction above which an update evaluates a second time).  ``--rom FILE`` reuses a
trained ROM (its stored validation table is printed; held-out commands are not re-solved unless
``--revalidate N``: N other held-out commands, seed :data:`REVALIDATION_SEED`, solved by the FE
and by this code's reduced model from a reset, as training validates);
``--against FILE ...`` times other ROMs of the same config in turn with it, round after round,
in this process (between processes the spread of the medians, 15-50 % here, hides differences
that one process shows; their errors: a ``--rom`` run of each).
Not a test: numbers for the notes, with the machine's load (``uptime``) printed next to them.
"""

from __future__ import annotations

import argparse
import itertools
import os
import time

import numpy as np

from dea_array_twin import ArrayConfig, ArrayTwin, NewtonSettings
from dea_array_twin.blasthreads import single_threaded_blas
from dea_array_twin.cli.rom import summary_lines
from dea_array_twin.model.reduced import Envelope
from dea_array_twin.model.reduced_twin import ReducedTwin
from dea_array_twin.rom.train import solve_snapshots, train, validate
from dea_array_twin.romfile import load_rom, save_rom


def grid(rows: int, cols: int) -> ArrayConfig:
    """The default 1x3, or a rows x cols grid in a square-ish frame with Table 1's 15 mm edge distance."""
    base = ArrayConfig()
    if (rows, cols) == (1, 3):
        return base
    size = lambda n: n * base.electrode_diameter + (n - 1) * base.spacing + 0.030  # noqa: E731
    return base.replace(rows=rows, cols=cols, length=size(cols), width=size(rows))


def load() -> str:
    return "load average %.2f %.2f %.2f" % os.getloadavg()


def trajectory(envelope: Envelope, steps: int, step: float, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """A reflected random walk through the envelope: ``step`` [m] per update on every driven indenter and
    the same fraction of the voltage range on every voltage; directions re-drawn with probability 0.05."""
    rng = np.random.default_rng(seed)
    k = envelope.driven
    lo = np.concatenate([envelope.displacement_min[k], envelope.voltage_min])
    hi = np.concatenate([envelope.displacement_max[k], envelope.voltage_max])
    span = np.where(hi > lo, hi - lo, 1.0)
    rate = step / (envelope.displacement_max[k] - envelope.displacement_min[k]).max()
    x = lo + rng.uniform(0.2, 0.8, lo.size) * (hi - lo)
    direction = rng.choice([-1.0, 1.0], lo.size)
    out = []
    for _ in range(steps):
        redraw = rng.random(lo.size) < 0.05
        direction[redraw] = rng.choice([-1.0, 1.0], redraw.sum())
        x = x + direction * rate * span
        low, high = x < lo, x > hi
        x = np.where(low, 2 * lo - x, np.where(high, 2 * hi - x, x))
        direction[low | high] *= -1
        out.append(x.copy())
    out = np.array(out)
    d = np.zeros((steps, envelope.n_units))
    d[:, k] = out[:, :k.size]
    return d, out[:, k.size:]


#: The actuator kinds' bias (an LBS holding the middle unit mid-envelope at mid-voltage), force amplitude [N],
#: moving mass [kg] and time step [s].
LBS = {"type": "linear", "stiffness": 40.0, "free_position": 0.01075}
FORCE, MASS, DT = 0.02, 0.005, 1e-3


def kind_setup(cfg: ArrayConfig, kind: str) -> tuple[ArrayConfig, tuple[str, ...] | None, float | None]:
    """Config, unit modes (None: the trained ones) and time step (None: quasi-static) of a timing kind."""
    if kind == "driven":
        return cfg, None, None
    modes = ["driven"] * cfg.n_units
    modes[cfg.n_units // 2] = "biased"
    mass = MASS if kind == "dynamic" else 0.0
    return cfg.replace(bias=(LBS,), mass=(mass,)), tuple(modes), DT if kind == "dynamic" else None


def updater(twin, modes: tuple[str, ...] | None, dt: float | None, d: np.ndarray, v: np.ndarray):
    """``run(i)``: the twin's update to command i of a path (a solve, or a step of ``dt``), with the force command
    of the actuator kinds on the biased unit."""
    if modes is None:
        return lambda i: twin.solve(d[i], v[i])
    f = np.zeros(d.shape)
    f[:, np.array(modes) == "biased"] = FORCE * np.sin(2 * np.pi * np.arange(len(d)) / 200.0)[:, None]
    if dt is None:
        return lambda i: twin.solve(d[i], v[i], modes, force=f[i])
    return lambda i: twin.step(dt, d[i], v[i], f[i], modes) if i else twin.solve(d[i], v[i], modes, force=f[i])


def compare(cfg: ArrayConfig, rom, d: np.ndarray, v: np.ndarray, kind: str = "driven",
            second_step: float | None = None) -> tuple:
    """Reduced and FE twins along one path: force and capacitance errors of the ROM, its position errors [m],
    FE times [ms], whether its (scaled) indicator was above the ROM's tolerance (an update the
    ROM's own tolerance would have sent to the FE; here the ROM answers every update), and the FE's
    (force, capacitance) of every update."""
    cfg, modes, dt = kind_setup(cfg, kind)
    twin = ReducedTwin(cfg, rom, tolerance=np.inf, second_step=second_step)
    fe = ArrayTwin(cfg, NewtonSettings(check_stability=False))
    run, run_fe = updater(twin, modes, dt, d, v), updater(fe, modes, dt, d, v)
    force, cap, position, fe_ms, flagged, truth = [], [], [], [], [], []
    for i in range(len(d)):
        res = run(i)
        flagged.append(res.error_indicator > rom.tolerance)
        tic = time.perf_counter()
        ref = run_fe(i)
        fe_ms.append(1e3 * (time.perf_counter() - tic))
        truth.append((ref.force, ref.capacitance))
        f_err, c_err = errors_of(rom, res.force, res.capacitance, ref.force, ref.capacitance)
        force.append(f_err)
        cap.append(c_err)
        position.append(np.abs(res.position - ref.position))
    return (np.array(force[1:]), np.array(cap[1:]), np.array(position[1:]), np.array(fe_ms[1:]),
            np.array(flagged[1:]), truth)


def output_errors(rom, outputs: list, truth: list) -> tuple[float, float]:
    """Largest force error and capacitance error (:func:`errors_of`) of a timed run's ``outputs`` (updates 1, 2,
    ... of a path) against the FE's ``truth`` (updates 0, 1, ...)."""
    pairs = [errors_of(rom, f, c, *truth[i + 1]) for i, (f, c) in enumerate(outputs)]
    return max(float(p[0].max()) for p in pairs), max(float(p[1].max()) for p in pairs)


def errors_of(rom, force: np.ndarray, capacitance: np.ndarray, fe_force: np.ndarray,
              fe_capacitance: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per unit: force error over the unit's force reference, capacitance error relative to the FE's."""
    return np.abs(force - fe_force) / rom.force_reference, np.abs(capacitance - fe_capacitance) / fe_capacitance


def time_updates(cfg: ArrayConfig, rom, d: np.ndarray, v: np.ndarray, background: bool, kind: str = "driven",
                 second_step: float | None = None, pace: float = 0.0,
                 blas: bool | None = None) -> tuple[np.ndarray, np.ndarray, dict]:
    """The ROM alone along one path (as a control loop runs it): wall and process CPU ms per update after the
    first (the CPU time leaves out the time other processes held the core, and counts the refresh worker);
    with ``pace`` [Hz] one update per period of a steady clock, else back to back.  The counts include the
    outputs (force, capacitance) of every timed update: with the refresh in a worker they depend on how far
    it lags, so they are judged from this run, not from :func:`compare`'s (where the FE's solves between
    the updates give the worker time).  ``blas``: the twin's (None: its default)."""
    cfg, modes, dt = kind_setup(cfg, kind)
    twin = ReducedTwin(cfg, rom, tolerance=np.inf, background_refresh=background, second_step=second_step,
                       blas=blas)
    run = updater(twin, modes, dt, d, v)
    run(0)
    start = (twin.evaluations, twin.refreshes)
    ms, cpu, outputs = [], [], []
    due = time.perf_counter()
    for i in range(1, len(d)):
        if pace > 0:
            due += 1.0 / pace
            time.sleep(max(0.0, due - time.perf_counter()))
        tic, tic_cpu = time.perf_counter(), time.process_time()
        res = run(i)
        ms.append(1e3 * (time.perf_counter() - tic))
        cpu.append(1e3 * (time.process_time() - tic_cpu))
        outputs.append((res.force, res.capacitance))
    twin.close()
    return np.array(ms), np.array(cpu), {"evaluations": twin.evaluations - start[0],
                                         "refreshes": twin.refreshes - start[1],
                                         "fallbacks": sum(twin.fallbacks.values()), "outputs": outputs,
                                         "threads": twin.threads, "helped": twin.team.helped,
                                         "taken_over": twin.team.taken_over}


#: Seed of ``--revalidate``'s commands: ``rom train`` draws its training, held-out and calibration samples with
#: seeds 0, 1 and 2 (by default), so these are other commands.
REVALIDATION_SEED = 7


def revalidate(cfg: ArrayConfig, rom, count: int, workers: int) -> str:
    """The error table of ``rom`` with this code on ``count`` held-out commands of its envelope (one line)."""
    d, v = rom.envelope.sample(count, REVALIDATION_SEED)
    tic = time.perf_counter()
    snaps, failures, _ = solve_snapshots(cfg, rom.envelope.modes, d, v, workers)
    fe_s = time.perf_counter() - tic
    t = validate(ReducedTwin(cfg, rom, tolerance=np.inf), snaps).table(rom.tolerance)
    return (f"re-validation with this code on {t['commands']} other held-out commands (seed {REVALIDATION_SEED}; "
            f"FE {fe_s:.0f} s{f', {len(failures)} FE failures left out' if failures else ''}): force error max "
            f"{t['force_error_max']:.4%} mean {t['force_error_mean']:.5%}; capacitance error max "
            f"{t['capacitance_error_max']:.4%} mean {t['capacitance_error_mean']:.5%}; {t['over_tolerance']} above "
            f"the tolerance ({t['over_tolerance_unflagged']} not flagged), {t['rom_fallbacks']} handed to the FE; "
            f"{load()}")


def main_node(rom_file: str, seconds: float, check_rate: float, priority: int = 0) -> None:
    """The node with the ROM at update_rate 1000 on a 1 Hz sine command: the share of ticks it publishes."""
    import math

    from bench_core import _cpu_seconds
    from tick_floor import describe, floor

    from dea_array_twin.ros.testing import TwinHarness

    rom_file = os.path.abspath(rom_file)  # the node runs from this checkout (below)
    rate = 1000.0
    params = {"update_rate": rate, "marker_rate": 0.0, "model": "rom", "rom_file": str(rom_file),
              "fe_check_rate": check_rate, "realtime_priority": priority}
    print(f"node: model rom ({rom_file}), update_rate {rate:g} Hz, fe_check_rate {check_rate:g} Hz, realtime_priority "
          f"{priority}, commands at "
          f"{rate:g} Hz; {seconds:g} s measured after 3 s; {load()} at start")
    print("  " + describe(rate, floor(rate, seconds, priority), priority))
    if priority > 0:  # the controller's side real-time too, as on a real-time rig
        from dea_array_twin.ros.realtime import use_fifo

        use_fifo(priority)
    # The node process (python -m) imports from its working directory first: run it from this checkout, so
    # that the node measured is this file's code, whichever directory the benchmark was started from.
    os.chdir(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
    with TwinHarness(parameters=params, process=True) as h:
        h.send_voltage([1000.0] * 3)
        start = time.monotonic()
        window = None
        tick = start
        while time.monotonic() - start < seconds + 3.0:
            t = time.monotonic() - start
            h.send_displacement([0.0075 + 0.005 * math.sin(2 * math.pi * (t + k / 3.0)) for k in range(3)])
            if window is None and t >= 3.0:
                h.clear()
                window, node_cpu, sender_cpu = time.monotonic(), _cpu_seconds(h.process.pid), time.process_time()
            tick += 1.0 / rate
            time.sleep(max(0.0, tick - time.monotonic()))
        elapsed = time.monotonic() - window
        node_cpu = (_cpu_seconds(h.process.pid) - node_cpu) / elapsed
        sender_cpu = (time.process_time() - sender_cpu) / elapsed
        forces = len(h.messages("force"))
        diags = h.messages("/diagnostics")
    values = {kv.key: kv.value for kv in diags[-1].status[0].values} if diags else {}
    keys = ("scheduling", "blas_single_threaded", "rom_hessian", "updates_per_s", "skipped_ticks",
            "solve_time_p50_ms", "solve_time_p95_ms",
            "solve_time_max_ms", "rom_updates", "rom_refreshes", "rom_fallbacks_envelope", "rom_fallbacks_indicator",
            "rom_resyncs", "fe_checks", "fe_check_ms", "rom_fe_force_difference_max",
            "rom_fe_capacitance_difference_max")
    print(f"  force messages {forces} in {elapsed:.2f} s = {forces / elapsed:.1f} /s: "
          f"{100 * forces / (rate * elapsed):.1f} % of the ticks (goal >= 99 %); {load()} at the end")
    print(f"  CPU: the node process {node_cpu:.2f} of a core, this process (sending the commands, receiving the "
          f"outputs) {sender_cpu:.2f}")
    print("  last diagnostics: " + ", ".join(f"{k} {values.get(k)}" for k in keys))
    print("  " + describe(rate, floor(rate, seconds, priority), priority) + " (after)")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--size", default="1x3", help="rows x cols (default 1x3, the paper's array)")
    parser.add_argument("--snapshots", type=int, default=240)
    parser.add_argument("--modes", type=int, default=30)
    parser.add_argument("--validation", type=int, default=200)
    parser.add_argument("--workers", type=int, default=1)
    parser.add_argument("--tolerance", type=float, default=1e-3)
    parser.add_argument("--step", type=float, default=1e-4, help="indenter step per update on the paths [m]")
    parser.add_argument("--paths", type=int, default=3, help="warm trajectories (default 3)")
    parser.add_argument("--length", type=int, default=400, help="updates per trajectory (default 400)")
    parser.add_argument("--kinds", default="driven,biased,dynamic",
                        help="update kinds on the paths: driven, biased, dynamic (default all three)")
    parser.add_argument("--rounds", type=int, default=1,
                        help="timing rounds, each timing every kind in turn (default 1)")
    parser.add_argument("--second-step", type=float,
                        help="ReducedTwin's second_step on the paths (default: its own, the tolerance, at most 1e-3)")
    parser.add_argument("--pace", type=float, default=0.0,
                        help="time the updates at this rate [Hz], as a control loop runs them (default 0: back to "
                             "back)")
    parser.add_argument("--edges", type=float, default=0.0,
                        help="share of the training commands stretched towards the envelope's bounds (default 0)")
    parser.add_argument("--rom", help="use this trained ROM file instead of training")
    parser.add_argument("--revalidate", type=int, default=0, metavar="N",
                        help="with --rom: validate it again with this code on N other held-out commands")
    parser.add_argument("--save", help="write the trained ROM here")
    parser.add_argument("--against", nargs="+", default=[], metavar="FILE",
                        help="with --rom: other ROM files of the config, timed in turn with it in every round")
    parser.add_argument("--threaded-blas", action="store_true",
                        help="leave OpenBLAS its threads (the worker's Hessians then per point), as before stop 30")
    parser.add_argument("--node", type=float, metavar="SECONDS", help="measure the node with --rom instead")
    parser.add_argument("--fe-check-rate", type=float, default=1.0, help="--node: FE checks per second (default 1)")
    parser.add_argument("--realtime-priority", type=int, default=0,
                        help="--node: the node's realtime_priority (SCHED_FIFO; default 0, normal scheduling)")
    args = parser.parse_args()
    if args.node:
        if not args.rom:
            parser.error("--node needs --rom")
        main_node(args.rom, args.node, args.fe_check_rate, args.realtime_priority)
        return
    if args.against and not args.rom:
        parser.error("--against needs --rom")
    if args.revalidate and not args.rom:
        parser.error("--revalidate needs --rom (training validates on --validation commands)")
    rows, cols = (int(n) for n in args.size.split("x"))
    cfg = grid(rows, cols)
    print(f"dea_array_twin ROM benchmark: {args.size}, default mesh; {load()} on {os.cpu_count()} cores")
    if args.rom:
        rom = load_rom(args.rom, cfg)
    else:
        envelope = Envelope.box(("driven",) * cfg.n_units, (0.0, 0.75 * cfg.scaled("electrode_diameter")),
                                (0.0, cfg.hv_voltage()))
        tic = time.perf_counter()
        result = train(cfg, envelope, args.snapshots, args.modes, args.tolerance, args.validation,
                       workers=args.workers, edges=args.edges, say=lambda text: print(f"  {text}", flush=True))
        rom = result.rom
        print(f"training: {time.perf_counter() - tic:.0f} s wall with {args.workers} worker(s) "
              f"(FE snapshots {result.timings['snapshots_s']:.0f} s, {result.timings['snapshots_cpu_s']:.0f} CPU s; "
              f"build {result.timings['build_s']:.0f} s; "
              f"FE calibration {result.timings.get('calibration_s', 0.0):.0f} s; "
              f"FE validation {result.timings['validation_fe_s']:.0f} s); "
              f"{load()}")
        if args.save:
            print(f"saved {save_rom(rom, args.save)}")
    print("\n".join(summary_lines(rom)))
    if args.revalidate:
        print(revalidate(cfg, rom, args.revalidate, args.workers), flush=True)
    pinned = not args.threaded_blas and single_threaded_blas()  # after training: its build uses every thread
    print(f"BLAS: {'one thread (the worker refreshes by BLAS products, as the node)' if pinned else 'its own threads'}")
    print(f"\nwarm trajectories: {args.paths} x {args.length} updates, {args.step * 1e3:g} mm per update per "
          f"indenter" + (f", second_step {args.second_step:g}" if args.second_step is not None else "")
          + f"; {load()}")
    paths = [trajectory(rom.envelope, args.length, args.step, seed) for seed in range(args.paths)]
    kinds = args.kinds.split(",")
    truth = {}  # kind -> per path, the FE's outputs of every update
    for kind in kinds:
        print(f" {kind}" + ("" if kind == "driven" else f" (unit {cfg.n_units // 2 + 1}: LBS {LBS}, force "
                                                        f"{FORCE:g} N sin, mass {MASS if kind == 'dynamic' else 0:g} kg"
                                                        + (f", dt {DT:g} s)" if kind == "dynamic" else ")")))
        errors = [compare(cfg, rom, d, v, kind, args.second_step) for d, v in paths]
        truth[kind] = [e[5] for e in errors]
        force, cap, position, fe_ms, flagged = (np.concatenate([e[i] for e in errors]) for i in range(5))
        over = np.maximum(force.max(axis=1), cap.max(axis=1)) > rom.tolerance
        print(f"  errors against the FE's warm updates: force max {force.max():.4%} mean {force.mean():.5%}; "
              f"capacitance max {cap.max():.4%} mean {cap.mean():.5%}; position max {position.max() * 1e6:.3g} um; "
              f"FE warm update median {np.median(fe_ms):.2f} ms; indicator above the tolerance on "
              f"{int(flagged.sum())} of {flagged.size} updates (the FE would answer those); "
              f"{int(over.sum())} update(s) with an error above the tolerance, {int((over & ~flagged).sum())} "
              f"of them not flagged")
    timed = [(args.rom, rom)] + [(name, load_rom(name, cfg)) for name in args.against]
    for round_ in range(1, args.rounds + 1):  # the kinds' (and ROMs') timings interleaved, round after round
        print(f" timing, round {round_} of {args.rounds}")
        for kind, (name, timed_rom), background in itertools.product(kinds, timed, (False, True)):
            runs = [time_updates(cfg, timed_rom, d, v, background, kind, args.second_step, args.pace,
                                 blas=pinned if background else None) for d, v in paths]
            ms, cpu = (np.concatenate([r[i] for r in runs]) for i in (0, 1))
            n = ms.size
            errs = [output_errors(timed_rom, r[2]["outputs"], t) for r, t in zip(runs, truth[kind])]
            where = "in a worker thread" if background else "in the calling thread"
            where += f", updates at {args.pace:g} Hz" if args.pace > 0 else ""
            which = f" [{os.path.basename(name)}]" if args.against else ""
            print(f"  {kind}{which}: ROM update, refresh {where}: "
                  f"median {np.median(ms):.3f} ms, mean {ms.mean():.3f}, p99 {np.percentile(ms, 99):.3f}, max "
                  f"{ms.max():.2f} ms (CPU: median {np.median(cpu):.3f}, mean {cpu.mean():.3f} ms); "
                  f"{sum(r[2]['evaluations'] for r in runs) / n:.2f} evaluations per update, "
                  f"{sum(r[2]['refreshes'] for r in runs)} refreshes, {sum(r[2]['fallbacks'] for r in runs)} "
                  f"fallbacks in {n} updates; {helpers(runs)}errors of these updates against the FE: force max "
                  f"{max(e[0] for e in errs):.4%}, capacitance max {max(e[1] for e in errs):.4%}; {load()}")


def helpers(runs: list) -> str:
    """What the twins' helper threads did (empty for twins with one thread)."""
    if runs[0][2]["threads"] == 1:
        return ""
    return (f"{runs[0][2]['threads']} threads, the helpers took {sum(r[2]['helped'] for r in runs)} chunks "
            f"({sum(r[2]['taken_over'] for r in runs)} taken over by the caller); ")


if __name__ == "__main__":
    main()

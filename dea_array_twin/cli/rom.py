"""``dea-twin rom``: train a reduced-order model (kHz twin) from the FE, or show what a ROM file holds.

``train [CONFIG] --out ROM.npz``  sample the envelope, solve FE snapshots (here, on
                                  ``--workers N`` processes or on Dask), build the basis
                                  and the hyper-reduction, validate on held-out commands
``info ROM.npz``                  the envelope, sizes and validation table of a file

Exit codes: 0 ok; 1 the validated error exceeds ``--tolerance`` (the ROM is written
all the same, the summary says so) or no snapshot converged; 2 bad arguments, config or
file.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

from ..configfile import load_config
from ..model.config import ArrayConfig, ConfigError
from ..model.reduced import Envelope, ReducedModel
from ..model.solver import ConvergenceError
from ..parallel import ExecutorError
from ..romfile import RomFileError, load_rom, save_rom
from .argtypes import float_list, word_list


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Add ``rom train`` and ``rom info`` to ``parser``."""
    kinds = parser.add_subparsers(dest="rom", required=True)
    train = kinds.add_parser("train", help="train a ROM from FE snapshots and validate it on held-out commands")
    train.add_argument("config", nargs="?", help="config YAML (default: the paper's 1-by-3 array)")
    train.add_argument("--out", required=True, help="ROM file to write (.npz)")
    train.add_argument("--modes", type=int, default=30, help="POD modes r (default 30)")
    train.add_argument("--tolerance", type=float, default=1e-3,
                       help="relative error the ROM must hold: force over its full scale, capacitance over its "
                            "value; updates whose indicator exceeds it go to the FE (default 1e-3 = 0.1%%)")
    train.add_argument("--snapshots", type=int, default=240, help="FE training snapshots (default 240)")
    train.add_argument("--validation", type=int, default=60, help="held-out commands to validate on (default 60)")
    train.add_argument("--calibration", type=int,
                       help="commands that calibrate the error indicator against the FE (default: as many as "
                            "--validation; 0: the raw indicator)")
    train.add_argument("--displacement-range", type=float_list(count=2, example="0,0.015"),
                       help="indenter displacement range of every driven unit [m] (default 0 to 0.75 D)")
    train.add_argument("--voltage-range", type=float_list(count=2, example="0,2730"),
                       help="voltage range of every unit [V] (default 0 to the eq. 14 voltage)")
    train.add_argument("--unit-modes", type=word_list,
                       help="per-unit mode, 'driven' or 'free', comma separated (default: the config's "
                            "unit_modes)")
    train.add_argument("--edges", type=float, default=0.0,
                       help="share of the training commands drawn with the Chebyshev density, dense near the "
                            "envelope's bounds (default 0: all uniform, Latin hypercube)")
    train.add_argument("--seed", type=int, default=0,
                       help="sampling seed (validation uses seed + 1, calibration seed + 2)")
    where = train.add_mutually_exclusive_group()
    where.add_argument("--workers", type=int, default=1, help="local worker processes for the FE snapshots")
    where.add_argument("--scheduler", metavar="ADDRESS", help="Dask distributed scheduler for the FE snapshots")
    info = kinds.add_parser("info", help="envelope, sizes and validation table of a ROM file")
    info.add_argument("rom_file", help="ROM file (.npz)")


def _envelope(cfg: ArrayConfig, args: argparse.Namespace) -> Envelope:
    modes = tuple(args.unit_modes or cfg.modes)
    d = args.displacement_range or (0.0, 0.75 * cfg.scaled("electrode_diameter"))
    v = args.voltage_range or (0.0, cfg.hv_voltage())
    if max(abs(d[0]), abs(d[1])) > cfg.scaled("max_displacement"):
        raise ConfigError(f"--displacement-range {list(d)} m exceeds max_displacement "
                          f"{cfg.scaled('max_displacement')} m")
    from ..model.membrane import check_modes

    return Envelope.box(check_modes(modes, cfg.n_units), d, v)


def summary_lines(rom: ReducedModel) -> list[str]:
    """What a ROM holds and how well it validated, as printable lines (SI, mm, %)."""
    env, facts = rom.envelope, rom.validation
    k = env.driven
    lines = [f"envelope: modes {','.join(env.modes)}; displacement "
             + (f"[{env.displacement_min[k].min() * 1e3:g}, {env.displacement_max[k].max() * 1e3:g}] mm"
                if k.size else "none (no driven unit)")
             + f"; voltage [{env.voltage_min.min():g}, {env.voltage_max.max():g}] V",
             f"model: {rom.n_modes} POD modes, {rom.enrichment.shape[1]} enrichment vectors, {rom.n_points} sampled "
             f"points (+{rom.point_weight.size - rom.n_points} monitor), {rom.basis.shape[0]} FE dofs; "
             f"tolerance {rom.tolerance:g}"]
    if "commands" in facts:
        t = facts.get("timings", {})
        calibrated = (f"scaled by {rom.indicator_scale:.3g}, calibrated on {facts['calibration_commands']} commands"
                      if facts.get("calibration_commands") else "raw, not calibrated")
        lines += [
            f"training: {facts['snapshots']} snapshots ({facts['snapshot_failures']} failed"
            + (f"; {facts['edges']:.0%} of the commands dense at the envelope's bounds" if facts.get("edges") else "")
            + ") in "
            f"{t.get('snapshots_s', float('nan')):.0f} s ({t.get('snapshots_cpu_s', float('nan')):.0f} CPU s); "
            f"basis + hyper-reduction {t.get('build_s', float('nan')):.0f} s (ECSW error "
            f"{facts['hr_relative_error']:.1e} on {facts['hr_snapshots']} snapshots)",
            f"validation on {facts['commands']} held-out commands: force error max {facts['force_error_max']:.3%} "
            f"mean {facts['force_error_mean']:.4%} (of each unit's largest |F|); capacitance error max "
            f"{facts['capacitance_error_max']:.3%} mean {facts['capacitance_error_mean']:.4%} "
            f"(dC: max {facts['delta_capacitance_error_max']:.2%} of its range)",
            f"indicator ({calibrated}): max {facts['indicator_max']:.2e}; {facts['flagged']} command(s) above "
            f"tolerance, {facts['over_tolerance']} with an error above it ({facts['over_tolerance_unflagged']} not "
            f"flagged); "
            f"reduced cold solve {facts['cold_solve_ms_median']:.1f} ms (median)"]
    if facts.get("rom_fallbacks"):
        lines.append(f"the reduced model handed {facts['rom_fallbacks']} of the {facts['commands']} held-out commands "
                     f"to the FE (its Newton did not converge there): the errors above are of the others")
    return lines


def run_from_args(args: argparse.Namespace) -> int:
    """Run ``dea-twin rom ...``; returns the exit code."""
    if args.rom == "info":
        try:
            rom = load_rom(args.rom_file)
        except (RomFileError, ValueError) as exc:
            print(f"dea-twin rom: error: {exc}", file=sys.stderr)
            return 2
        print("\n".join([f"{args.rom_file}: config hash {rom.config_hash}"] + summary_lines(rom)))
        warning = rom.validation_warning()
        if warning:
            print(f"dea-twin rom: warning: {warning}", file=sys.stderr)
        return 0
    from tqdm import tqdm

    from ..rom.train import train

    try:
        cfg = load_config(args.config)
        for name in ("modes", "snapshots", "validation", "workers"):
            if getattr(args, name) < 1:
                raise ConfigError(f"--{name} must be >= 1, got {getattr(args, name)}")
        if args.calibration is not None and args.calibration < 0:
            raise ConfigError(f"--calibration must be >= 0, got {args.calibration}")
        if not 0 <= args.edges <= 1:
            raise ConfigError(f"--edges must be a share in [0, 1], got {args.edges}")
        if not 0 < args.tolerance < 1:
            raise ConfigError(f"--tolerance must be in (0, 1), got {args.tolerance}")
        envelope = _envelope(cfg, args)
        out = Path(args.out)
        if not out.parent.is_dir():
            raise ConfigError(f"--out: folder {out.parent} does not exist")
        where = f"Dask at {args.scheduler}" if args.scheduler else f"{args.workers} worker(s)"
        bars: dict[str, tqdm] = {}

        def progress(stage: str, done: int, total: int) -> None:
            if stage not in bars:
                bars[stage] = tqdm(total=total, desc=f"FE {stage} ({where})", unit="solve", file=sys.stderr,
                                   disable=None)
            bars[stage].update(done - bars[stage].n)
            if done == total:
                bars[stage].close()

        tic = time.perf_counter()
        result = train(cfg, envelope, args.snapshots, args.modes, args.tolerance, args.validation, args.seed,
                       args.workers, args.scheduler, progress,
                       lambda text: print(f"dea-twin rom: {text}", file=sys.stderr), args.calibration,
                       args.edges)
        path = save_rom(result.rom, out)
    except (ConfigError, ValueError, ExecutorError, OSError) as exc:
        print(f"dea-twin rom: error: {exc}", file=sys.stderr)
        return 2
    except ConvergenceError as exc:
        print(f"dea-twin rom: error: {exc}", file=sys.stderr)
        return 1
    for failure in result.failures:
        print(f"dea-twin rom: warning: FE snapshot left out: {failure}", file=sys.stderr)
    print("\n".join(summary_lines(result.rom)))
    print(f"written: {path} ({path.stat().st_size / 1e6:.1f} MB) in {time.perf_counter() - tic:.0f} s")
    worst = max(result.rom.validation["force_error_max"], result.rom.validation["capacitance_error_max"])
    if worst > args.tolerance:
        print(f"dea-twin rom: the validated error {worst:.3%} exceeds --tolerance {args.tolerance:.3%}: "
              "train with more --modes or --snapshots, or a smaller envelope", file=sys.stderr)
        return 1
    return 0

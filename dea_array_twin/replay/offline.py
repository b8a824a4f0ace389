"""Re-simulate a recorded run: the twin on a bag's commands, offline or republished live.

``dea-twin replay BAG`` reads the per-unit commands of a recording (a single ``.mcap``
file or a rosbag2 directory of them), re-runs :class:`~dea_array_twin.model.twin.ArrayTwin` on them as fast
as it can and writes what the twin answers; ``dea-twin replay --realtime BAG`` instead
republishes the recorded commands with their original timing, for a controller or a
live twin in the loop without ``ros2 bag play``.  This module holds the offline replay
(:func:`replay_commands`, :func:`compare_outputs`, the MCAP and CSV outputs,
:func:`replay_offline`); the options are in :mod:`dea_array_twin.cli.replay`; the bag
is read by :class:`~dea_array_twin.bag.reader.Bag`, its topics chosen by
:mod:`~dea_array_twin.bag.topics`, its config by
:func:`~dea_array_twin.bag.twin_config.resolve_config`, and ``--realtime`` runs
:func:`~.realtime.realtime_replay`.

Bag contract (what the twin's recorder writes; a rig recorded with ``ros2 bag record -s
mcap`` has the command topics only):

* ``command/displacement``, ``command/voltage``: ``std_msgs/msg/Float64MultiArray``,
  one value per unit [m], [V]; any namespace (``/left_array/command/voltage``), or any
  other name mapped with ``--topic-map OLD=NEW``;
* recorded outputs ``force``, ``capacitance`` (Float64MultiArray), used for the FIT;
* metadata record ``dea_array_twin_config``: every :class:`~dea_array_twin.model.config.ArrayConfig` field
  as ``str(value)``, plus ``unit_modes`` (``"[driven, free, driven]"``) and
  ``update_rate``.

Offline replay (:func:`replay_commands`) is sample and hold: displacement and voltage
start at zero, each command message in log-time order replaces one of them and triggers
one solve.  Commands the twin node would reject (:func:`~dea_array_twin.model.twin.command_error`: wrong
length, NaN/inf, beyond ``max_displacement``, negative voltage, or a voltage at which the
flat membrane's field reaches ``breakdown_field``) are skipped and counted.  A command
without equilibrium is handled as the node handles it: the twin keeps its last state,
the command stays held, the failure is reported (the first few by time, then a count)
and the replay goes on with the next command (exit code 1 at the end).  Outputs, one
entry per successful solve:

* ``OUT.mcap``: ``/command/displacement`` or ``/command/voltage`` (the accepted command
  that triggered the solve), ``/force``, ``/capacitance`` (Float64MultiArray) and
  ``/unit_states`` (JointState: position = centre deflection [m], velocity = 0 (the
  model is quasi-static), effort = force [N]), each with log time = the command's log
  time, plus the ``dea_array_twin_config`` metadata actually used and a
  ``dea_array_twin_replay`` record (source, ``time_origin_ns``).  The output is itself a
  replayable, plottable bag;
* ``OUT.csv``: ``time_s`` (from the first message of the input bag), ``d1_m..``,
  ``V1_V..``, ``F1_N..``, ``C1_F..``.

If the bag holds recorded ``force``/``capacitance``, each recorded message is compared
with the replayed state current at its log time (the latest accepted command at or
before it; the zero command before the first one) and the paper's FIT (eq. 12, :func:`fit`)
is printed per unit and channel.  A recording of the live node at ``update_rate`` > 0
lags its commands by up to one tick, which costs a little FIT on fast command changes.

With ``--rom ROM.npz`` the replay runs the reduced twin
(:class:`~dea_array_twin.model.reduced_twin.ReducedTwin`, its FE answering outside
the envelope; the count of such fallbacks is printed; a dynamic run steps it at the
recorded ticks as the FE); ``--rom ROM.npz --compare`` also replays the FE on the same
commands (a dynamic run: the same steps) and prints the reduced model's largest force
difference (over each unit's largest FE |F|) and capacitance difference (over C) and the
FIT of its outputs against the FE's (:func:`compare_models`).

A file without a summary (the recorder was killed) is refused (see :mod:`~dea_array_twin.bag.reader`).

Exit codes: 0 ok, 1 some command had no equilibrium (the rest is replayed), 2 bad input
(missing or non-MCAP file, truncated bag, no command topics, bad config), 130
interrupted (``--realtime``).
"""

from __future__ import annotations

import csv
import math
import sys
import time
from collections import Counter
from collections.abc import Iterable, Iterator, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..bag.reader import Bag, BagError
from ..bag.series import csv_header
from ..bag.topics import (
    COMMANDS,
    FLOAT_ARRAY,
    OUTPUTS,
    command_topics,
    output_topics,
    select_topic,
)
from ..bag.twin_config import REPLAY_METADATA, metadata_from_config, resolve_config
from ..bag.writer import CONFIG_RECORD
from ..model.config import BIASED
from ..model.metrics import fit
from ..model.reduced_twin import ReducedTwin
from ..model.solver import ConvergenceError
from ..model.twin import ArrayTwin, command_error
from ..romfile import load_rom

__all__ = ["ReplayRun", "compare_outputs", "replay_commands", "replay_offline"]

JOINT_STATE = "sensor_msgs/msg/JointState"
_MAX_LISTED_WARNINGS = 5


# ------------------------------------------------------------- offline replay

@dataclass
class ReplayRun:
    """The twin's answers to a sequence of commands: one row per solve (SI units).

    Attributes
    ----------
    times_ns : ndarray, shape (k,)
        Log time of the command that triggered each solve, or the tick of each time step [ns].
    kinds : list of str
        ``"displacement"``, ``"voltage"`` or ``"force"``: which command triggered the
        solve; ``"step"`` for a time step of the dynamics.
    displacement, voltage, force, capacitance, centre_deflection : ndarray, shape (k, n)
        Held commands [m], [V] and outputs [N], [F], [m] after each solve.
    force_command, position : ndarray, shape (k, n)
        Held external force on biased indenters [N]; unit positions [m] (``unit_states``).
    initial_force, initial_capacitance, initial_position : ndarray, shape (n,)
        The state at the zero command, current before the first accepted command.
    skipped : Counter
        Rejected commands per kind.
    state_warnings : Counter
        Solves whose result carries a warning (wrinkling, field...), per warning kind.
    failures : list of str
        One line per command without equilibrium (time, command, why); the twin kept its
        last state there, as the node does.
    """

    times_ns: np.ndarray
    kinds: list[str]
    displacement: np.ndarray
    voltage: np.ndarray
    force: np.ndarray
    capacitance: np.ndarray
    centre_deflection: np.ndarray
    initial_force: np.ndarray
    initial_capacitance: np.ndarray
    skipped: Counter = field(default_factory=Counter)
    state_warnings: Counter = field(default_factory=Counter)
    failures: list[str] = field(default_factory=list)
    force_command: np.ndarray | None = None
    position: np.ndarray | None = None
    initial_position: np.ndarray | None = None

    @property
    def n_solves(self) -> int:
        """Number of solves (rows)."""
        return len(self.times_ns)


#: What each :attr:`.TwinResult.flags` entry means, for the replay's counts.
_FLAG_TEXT = {"unstable": "equilibrium not a stable minimum", "wrinkled": "compressive stress: the membrane would "
              "wrinkle", "field_exceeded": "electric field above breakdown_field"}


def replay_commands(twin: ArrayTwin, modes: Sequence[str], commands: Iterable[tuple[int, str, Sequence[float]]],
                    total: int | None = None, time_origin_ns: int = 0,
                    ticks_ns: Sequence[int] | None = None, dt: float = 0.0) -> ReplayRun:
    """Run the twin on commands in order, sample and hold: one solve per accepted command.

    Parameters
    ----------
    twin : ArrayTwin
        The twin (reset first).
    modes
        ``"driven"``/``"free"``/``"biased"`` per unit.
    commands
        ``(log_time_ns, kind, values)`` with kind ``"displacement"`` [m], ``"voltage"`` [V]
        or ``"force"`` [N], in log-time order.
    total
        Number of commands, for the progress bar.
    time_origin_ns
        Log time shown as t = 0 in messages.
    ticks_ns, dt
        A run of the dynamics (biased units with mass): the recording node's ticks [ns]
        (its ``unit_states`` stamps, the first its quasi-static rest state) and its update
        period [s].  Then each tick after the first is one time step of ``dt`` (times the
        periods since the last tick), with the commands logged before the tick, as the
        node took them; rows are steps, not commands.

    Returns
    -------
    ReplayRun
        What was computed; ``failures`` lists the commands without equilibrium (the run went on).
    """
    from tqdm import tqdm

    n = twin.n_units
    twin.reset()
    held = {kind: np.zeros(n) for kind in (*COMMANDS, "force")}
    first = twin.solve(held["displacement"], held["voltage"], modes, check_stability=False, force=held["force"])
    rows: dict[str, list] = {k: [] for k in ("t", "kind", "d", "v", "u", "f", "c", "z", "p")}
    skipped: Counter = Counter()
    state_warnings: Counter = Counter()
    failures: list[str] = []

    def record(when: int, kind: str, res) -> None:
        state_warnings.update(_FLAG_TEXT[flag] for flag in res.flags)
        rows["t"].append(int(when))
        rows["kind"].append(kind)
        rows["d"].append(held["displacement"].copy())
        rows["v"].append(held["voltage"].copy())
        rows["u"].append(held["force"].copy())
        rows["f"].append(np.asarray(res.force, dtype=float))
        rows["c"].append(np.asarray(res.capacitance, dtype=float))
        rows["z"].append(np.asarray(res.centre_deflection, dtype=float))
        rows["p"].append(np.asarray(res.position, dtype=float))

    def update(kind: str, values: list, when: int) -> None:
        """Hold an accepted command (and, quasi-statically, solve)."""
        t_s = (when - time_origin_ns) * 1e-9
        problem = command_error(kind, values, twin.config)
        if problem:
            skipped[kind] += 1
            if sum(skipped.values()) <= _MAX_LISTED_WARNINGS:
                bar.write(f"dea-twin replay: warning: skipping {kind} command at t = {t_s:.6f} s: {problem}",
                          file=sys.stderr)
            return
        held[kind] = np.asarray(values, dtype=float)
        if ticks_ns is None:
            solve(kind, when, f"{kind} command {values}")

    def solve(kind: str, when: int, what: str, steps: int = 0) -> None:
        try:
            if steps:
                res = twin.step(dt * steps, held["displacement"], held["voltage"], held["force"], modes,
                                check_stability=False)
            else:
                res = twin.solve(held["displacement"], held["voltage"], modes, check_stability=False,
                                 force=held["force"])
        except (ConvergenceError, ValueError) as exc:  # the node keeps its last state and goes on
            failures.append(f"t = {(when - time_origin_ns) * 1e-9:.6f} s ({what}): {exc}")
            if len(failures) <= _MAX_LISTED_WARNINGS:
                bar.write(f"dea-twin replay: warning: solve failed, keeping the last state: {failures[-1]}",
                          file=sys.stderr)
            return
        record(when, kind, res)

    bar = tqdm(total=total, desc="replay", unit="cmd", file=sys.stderr, disable=None)
    try:
        if ticks_ns is None:
            for log_time, kind, values in commands:
                bar.update(1)
                update(kind, list(values), log_time)
        else:
            stream = iter(commands)
            pending = next(stream, None)
            ticks = list(ticks_ns)
            for i, tick in enumerate(ticks):
                if i == 0:  # the node's first update: the quasi-static rest state at the zero command
                    solve("step", tick, "the rest state")
                    continue
                while pending is not None and pending[0] < tick:
                    bar.update(1)
                    update(pending[1], list(pending[2]), pending[0])
                    pending = next(stream, None)
                periods = max(1, int(round((tick - ticks[i - 1]) * 1e-9 / dt)))
                solve("step", tick, f"the step to tick {i}", periods)
    finally:
        bar.close()

    def stack(key: str) -> np.ndarray:
        return np.array(rows[key], dtype=float).reshape(-1, n)

    return ReplayRun(times_ns=np.array(rows["t"], dtype=np.int64), kinds=rows["kind"], displacement=stack("d"),
                     voltage=stack("v"), force=stack("f"), capacitance=stack("c"), centre_deflection=stack("z"),
                     force_command=stack("u"), position=stack("p"),
                     initial_force=np.asarray(first.force, dtype=float),
                     initial_capacitance=np.asarray(first.capacitance, dtype=float),
                     initial_position=np.asarray(first.position, dtype=float),
                     skipped=skipped, state_warnings=state_warnings, failures=failures)


def compare_outputs(run: ReplayRun, recorded: dict[str, tuple[np.ndarray, np.ndarray]],
                    lag_ns: int = 0) -> dict[str, np.ndarray]:
    """FIT per unit of the replayed outputs against recorded ones.

    Parameters
    ----------
    run
        The replay.
    recorded
        ``{"force": (times_ns, values), "capacitance": ...}``, values of shape (m, n).
    lag_ns
        Largest latency of the recorded outputs behind their commands [ns].  Each
        recorded message is compared with the replayed state current at its log time
        or, if one fits it better, with a state current up to ``lag_ns`` earlier (the
        live node answers a command at one of its next updates).  0 pairs each message
        with the latest solve at or before it (or the zero-command state before the first).

    Returns
    -------
    dict
        Kind -> FIT [%] per unit (``nan`` where the recorded signal is constant).
    """
    out = {}
    for kind, (times, values) in recorded.items():
        model_rows = np.vstack([getattr(run, f"initial_{kind}")[None, :], getattr(run, kind)])
        times = np.asarray(times, dtype=np.int64)
        last = np.searchsorted(run.times_ns, times, side="right")
        first = np.searchsorted(run.times_ns, times - int(lag_ns), side="right")
        idx = last.copy()
        for i in np.flatnonzero(first < last):  # several candidate states: take the closest
            candidates = np.arange(first[i], last[i] + 1)
            idx[i] = candidates[np.argmin(np.abs(model_rows[candidates] - values[i]).sum(axis=1))]
        model = model_rows[idx]
        out[kind] = np.array([fit(values[:, k], model[:, k]) for k in range(values.shape[1])])
    return out


# ------------------------------------------------------------------- outputs


def compare_models(rom: ReplayRun, fe: ReplayRun) -> dict[str, np.ndarray]:
    """The reduced replay against the FE replay of the same commands, per unit.

    Returns ``force_difference`` (largest |F_rom - F_fe| over the unit's largest FE |F|),
    ``capacitance_difference`` (largest |C_rom - C_fe| / C_fe) and the FIT [%] (eq. 12)
    of the reduced force and capacitance against the FE's.  Rows are paired by command
    (both replays solve the same accepted commands); a command one of them could not
    solve is left out.
    """
    common = np.intersect1d(rom.times_ns, fe.times_ns)
    a = np.searchsorted(rom.times_ns, common)
    b = np.searchsorted(fe.times_ns, common)
    f_rom, f_fe = rom.force[a], fe.force[b]
    c_rom, c_fe = rom.capacitance[a], fe.capacitance[b]
    scale = np.abs(f_fe).max(axis=0, initial=0.0)
    return {"force_difference": np.abs(f_rom - f_fe).max(axis=0, initial=0.0) / np.where(scale > 0, scale, 1.0),
            "capacitance_difference": (np.abs(c_rom - c_fe) / c_fe).max(axis=0, initial=0.0),
            "force_fit": np.array([fit(f_fe[:, k], f_rom[:, k]) for k in range(f_fe.shape[1])]),
            "capacitance_fit": np.array([fit(c_fe[:, k], c_rom[:, k]) for k in range(c_fe.shape[1])])}


def _comparison_table(diff: dict[str, np.ndarray], rows: int) -> str:
    lines = [f"reduced model against the FE on the same {rows} command(s):",
             "  unit  force diff [%]  capacitance diff [%]  force FIT [%]  capacitance FIT [%]"]
    for u in range(diff["force_difference"].size):
        cells = [f"{100 * diff['force_difference'][u]:14.4f}", f"{100 * diff['capacitance_difference'][u]:20.5f}"]
        cells += [f"{'n/a' if math.isnan(v) else f'{v:.4f}':>13}" for v in (diff["force_fit"][u],)]
        cells += [f"{'n/a' if math.isnan(v) else f'{v:.4f}':>19}" for v in (diff["capacitance_fit"][u],)]
        lines.append(f"  {u + 1:>4}  " + "  ".join(cells))
    return "\n".join(lines)


def write_mcap(path: Path, run: ReplayRun, metadata: dict[str, dict[str, str]]) -> None:
    """Write the replay as a ROS 2 MCAP bag (see the module docstring for the topics).

    Every sequence is filled (``serialize_message`` may append junk bytes to empty ones).
    """
    from rclpy.serialization import serialize_message
    from sensor_msgs.msg import JointState

    from ..bag.writer import Ros2McapWriter
    from ..ros.node import unit_array

    n = run.force.shape[1]
    names = [f"unit_{k + 1}" for k in range(n)]
    with Ros2McapWriter(path, metadata=metadata, flush_period=None, overwrite=True) as rec:
        commands = {"displacement": run.displacement, "voltage": run.voltage, "force": run.force_command}
        ids = {f"command/{kind}": rec.add_topic(f"/command/{kind}", FLOAT_ARRAY) for kind in commands}
        ids.update({kind: rec.add_topic(f"/{kind}", FLOAT_ARRAY) for kind in OUTPUTS})
        ids["unit_states"] = rec.add_topic("/unit_states", JOINT_STATE)
        for i, t in enumerate(run.times_ns.tolist()):
            kind = run.kinds[i]
            # the command that triggered the solve; for a time step, every command that changed
            changed = [kind] if kind in commands else [
                k for k, held in commands.items() if not np.array_equal(held[i], held[i - 1] if i else 0 * held[i])]
            for k in changed:
                rec.write(ids[f"command/{k}"], serialize_message(unit_array(commands[k][i])), t)
            rec.write(ids["force"], serialize_message(unit_array(run.force[i])), t)
            rec.write(ids["capacitance"], serialize_message(unit_array(run.capacitance[i])), t)
            states = JointState(name=names, position=[float(v) for v in run.position[i]],
                                velocity=[0.0] * n, effort=[float(v) for v in run.force[i]])
            states.header.stamp.sec, states.header.stamp.nanosec = divmod(t, 1_000_000_000)
            states.header.frame_id = "dea_array"
            rec.write(ids["unit_states"], serialize_message(states), t)


def write_csv(path: Path, run: ReplayRun, origin_ns: int) -> None:
    """Write the replay as CSV: one row per solve, time relative to ``origin_ns``, SI units."""
    n = run.force.shape[1]
    with open(path, "w", newline="") as f:
        writer = csv.writer(f)
        writer.writerow(csv_header(n))
        for i, t in enumerate(run.times_ns.tolist()):
            writer.writerow([round((t - origin_ns) * 1e-9, 9), *run.displacement[i].tolist(), *run.voltage[i].tolist(),
                             *run.force[i].tolist(), *run.capacitance[i].tolist()])


def _output_base(bag: Bag, out: str | None) -> Path:
    if out is not None:
        base = Path(out)
        return base.with_suffix("") if base.suffix in (".mcap", ".csv") else base
    return bag.output_path("_replay")


def default_fit_lag(bag: Bag) -> tuple[float, str]:
    """How late the recording node's outputs may be [s], and why: for ``--fit-lag`` when not given.

    The node answers a command when the solve that uses it ends: at its next update tick
    (up to one period) plus the solve time.  So the lag is the longer of three update
    periods and one period plus the longest solve the node's recorded ``/diagnostics``
    report (``solve_time_max_ms``, the longest of each 10 s); 0 for a bag without the
    twin's metadata (the outputs answer each command at once, as a replay's do).
    """
    rate = _recorded_rate(bag)
    if not rate > 0:
        return 0.0, "no update rate recorded: outputs answer each command at once"
    longest = 0.0
    topics = [t for t, type_name in bag.topics.items() if type_name.endswith("DiagnosticArray")]
    for msg in bag.messages(topics, decode=True):
        for status in msg.decoded.status:
            for kv in status.values:
                if kv.key == "solve_time_max_ms":
                    try:
                        value = float(kv.value) * 1e-3
                    except ValueError:
                        continue
                    if math.isfinite(value):
                        longest = max(longest, value)
    if 1.0 / rate + longest > 3.0 / rate:
        return 1.0 / rate + longest, (f"one update period of the recording node plus the longest solve its "
                                      f"diagnostics report, {longest * 1e3:.1f} ms")
    return 3.0 / rate, "three update periods of the recording node"


def _fit_table(fits: dict[str, np.ndarray], topics: dict[str, str], counts: dict[str, int],
               kinds: Sequence[str] = OUTPUTS) -> str:
    kinds = [k for k in kinds if k in fits]
    if not kinds:
        return ""
    n = len(fits[kinds[0]])
    head = ", ".join(f"{topics[k]} ({counts[k]} msgs)" for k in kinds)
    lines = [f"FIT [%] (paper eq. 12) of the replay against the recorded {head}:",
             "  unit" + "".join(f"  {k + ' [%]':>16}" for k in kinds)]
    for u in range(n):
        cells = "".join(f"  {'n/a' if math.isnan(fits[k][u]) else f'{fits[k][u]:.4f}':>16}" for k in kinds)
        lines.append(f"  {u + 1:>4}{cells}")
    if any(np.isnan(fits[k]).any() for k in kinds):
        lines.append("  n/a: the recorded signal is constant (e.g. a free unit's zero force): FIT undefined")
    return "\n".join(lines)


def _recorded_rate(bag: Bag) -> float:
    """The recording node's ``update_rate`` [Hz] from the bag's metadata (0 if absent or not a number)."""
    recorded_rate = (bag.metadata(CONFIG_RECORD) or {}).get("update_rate", "0")
    try:
        return float(recorded_rate)
    except ValueError:
        _log(f"warning: recorded update_rate {recorded_rate!r} is not a number; pass --fit-lag")
        return 0.0


def _unit_states(bag: Bag, commands: dict[str, str], n: int) -> tuple | None:
    """``(stamps_ns, log_times_ns, positions (m, n), topic)`` of the recorded ``unit_states``, or None.

    The topic ends with ``unit_states`` in the commands' namespace (or anywhere, if only one)."""
    candidates = [t for t, kind in bag.topics.items() if t.endswith("unit_states") and kind == JOINT_STATE]
    namespace = next((t[: -len(f"/command/{k}")] for k, t in commands.items() if t.endswith(f"/command/{k}")), "")
    preferred = [t for t in candidates if t == f"{namespace}/unit_states"]
    if len(preferred) == 1:
        topic = preferred[0]
    elif len(candidates) == 1:
        topic = candidates[0]
    else:
        return None
    stamps, logs, positions = [], [], []
    for msg in bag.messages([topic], decode=True):
        position = np.asarray(msg.decoded.position, dtype=float)
        if position.shape != (n,) or not np.all(np.isfinite(position)):
            continue
        stamp = msg.decoded.header.stamp
        stamps.append(stamp.sec * 1_000_000_000 + stamp.nanosec)
        logs.append(msg.log_time_ns)
        positions.append(position)
    if not positions:
        return None
    return np.array(stamps, dtype=np.int64), np.array(logs, dtype=np.int64), np.array(positions), topic


def _ticks(stamps: np.ndarray) -> np.ndarray:
    """The distinct tick stamps in order (an abandoned step republishes the last one)."""
    keep = np.concatenate([[True], np.diff(stamps) > 0]) if len(stamps) else np.zeros(0, dtype=bool)
    return stamps[keep]


def _tick_of(log_times: np.ndarray, states: tuple) -> np.ndarray:
    """The tick stamp of the ``unit_states`` published with each output (the last logged at or before it)."""
    index = np.clip(np.searchsorted(states[1], log_times, side="right") - 1, 0, len(states[0]) - 1)
    return states[0][index]


def _log(text: str) -> None:
    print(f"dea-twin replay: {text}", file=sys.stderr)


def replay_offline(bag: Bag, topic_map: dict[str, str], config_path: str | None, modes: Sequence[str] | None,
                   out: str | None, fit_lag: float | None = None, rom_path: str | None = None,
                   compare: bool = False) -> int:
    """``dea-twin replay BAG``: re-run the twin (the FE, or the ROM of ``rom_path``), write OUT.mcap and
    OUT.csv, print FIT (and with ``compare`` the ROM against the FE); the exit code."""
    if compare and rom_path is None:
        raise BagError("--compare needs --rom (it compares the reduced model with the FE)")
    commands = command_topics(bag, topic_map)
    outputs = output_topics(bag, commands, topic_map)
    force_topic = select_topic(bag.topics, "command/force", topic_map)
    if force_topic is not None:
        commands["force"] = force_topic
    cfg, modes, notes = resolve_config(bag, config_path, modes)
    for note in notes:
        _log(note)
    base = _output_base(bag, out)
    mcap_path, csv_path = base.with_name(base.name + ".mcap"), base.with_name(base.name + ".csv")
    if any(mcap_path.resolve() == p.resolve() for p in bag.files):
        raise BagError(f"the output {mcap_path} would overwrite the input; choose another --out")
    _log("commands from " + ", ".join(f"{t} ({bag.counts.get(t, 0)} msgs)" for t in commands.values()))
    twin = ArrayTwin(cfg) if rom_path is None else ReducedTwin(cfg, load_rom(rom_path, cfg))
    kind_of = {topic: kind for kind, topic in commands.items()}
    recorded: dict[str, tuple[list, list]] = {k: ([], []) for k in outputs}
    output_kind = {topic: kind for kind, topic in outputs.items()}
    bad_outputs: Counter = Counter()
    n = cfg.n_units

    streamed = list(commands.values()) + list(outputs.values())  # (outputs gains the positions below)

    def command_stream() -> Iterator[tuple[int, str, list[float]]]:
        for msg in bag.messages(streamed, decode=True):
            if msg.topic in kind_of:
                yield msg.log_time_ns, kind_of[msg.topic], list(msg.decoded.data)
            else:
                kind = output_kind[msg.topic]
                values = np.asarray(msg.decoded.data, dtype=float)
                if values.shape != (n,) or not np.all(np.isfinite(values)):
                    bad_outputs[kind] += 1
                    continue
                recorded[kind][0].append(msg.log_time_ns)
                recorded[kind][1].append(values)

    total = sum(bag.counts.get(t, 0) for t in commands.values()) or None
    origin = bag.start_ns or 0
    rate = _recorded_rate(bag)
    states = _unit_states(bag, commands, n)
    masses = cfg.per_unit("mass")
    dynamic = (rate > 0 and states is not None and len(states[0]) > 1
               and any(mode == BIASED and mass > 0 for mode, mass in zip(modes, masses)))
    if dynamic:
        _log(f"biased units with mass at {rate:g} Hz: re-simulating the dynamics, one step per recorded tick "
             f"({len(states[0])} unit_states stamps), each command from the first tick after it")
    tic = time.perf_counter()
    steps = {"ticks_ns": _ticks(states[0]) if dynamic else None, "dt": 1.0 / rate if dynamic else 0.0}
    run = replay_commands(twin, modes, command_stream(), total=total, time_origin_ns=origin, **steps)
    elapsed = time.perf_counter() - tic
    if rom_path is not None:
        print(f"reduced model {rom_path}: {twin.updates} update(s) by the ROM, FE fallbacks "
              + (", ".join(f"{k} {v}" for k, v in sorted(twin.fallbacks.items())) or "none"))
    for kind, count in run.skipped.items():
        _log(f"warning: skipped {count} invalid {kind} command(s)")
    for text, count in run.state_warnings.items():
        _log(f"warning: {count} replayed state(s) flagged: {text}")
    for kind, count in bad_outputs.items():
        _log(f"warning: {count} recorded {kind} message(s) of the wrong length or not finite: not compared")
    if run.n_solves == 0 and not run.failures:
        raise BagError(f"no valid command in {bag.path} ({sum(run.skipped.values())} rejected); "
                       f"does the config match the recording? (--config)")
    metadata = {CONFIG_RECORD: metadata_from_config(cfg, modes),
                REPLAY_METADATA: {"source": str(bag.path.resolve()), "time_origin_ns": str(origin),
                                  "config_source": notes[0], "solves": str(run.n_solves)}}
    write_mcap(mcap_path, run, metadata)
    write_csv(csv_path, run, origin)
    print(f"replayed {run.n_solves} command(s) in {elapsed:.2f} s "
          f"({sum(run.skipped.values())} skipped): wrote {mcap_path} and {csv_path}")
    if run.failures:
        _log(f"warning: {len(run.failures)} command(s) without equilibrium (the first: {run.failures[0]}); "
             "the twin kept its last state at each and went on, as the node does")
    data = {k: (np.array(t, dtype=np.int64), np.array(v, dtype=float).reshape(-1, n))
            for k, (t, v) in recorded.items() if t}
    if states is not None:  # positions: the tick stamps of a dynamic run, else the log times
        data["position"] = (np.asarray(states[0 if dynamic else 1], dtype=np.int64), states[2])
        outputs = {**outputs, "position": states[3]}
    if data:
        if dynamic:
            fit_lag = 0.0
            data = {k: (v if k == "position" else (_tick_of(v[0], states), v[1])) for k, v in data.items()}
            _log("FIT pairs each recorded output with the replayed step of its tick")
        else:
            if fit_lag is None:
                fit_lag, why = default_fit_lag(bag)
            else:
                why = "--fit-lag"
            _log(f"FIT pairs each recorded output with a replayed state current up to {fit_lag * 1e3:.1f} ms before "
                 f"it ({why}; --fit-lag to change)")
        fits = compare_outputs(run, data, int(round(fit_lag * 1e9)))
        counts = {k: len(v[0]) for k, v in data.items()}
        for kinds in (OUTPUTS, ("position",)):  # positions (unit_states) in a table of their own
            table = _fit_table(fits, outputs, counts, kinds)
            if table:
                print(table)
    if compare:
        fe_run = replay_commands(ArrayTwin(cfg), modes, ((t, k, v) for t, k, v in command_stream()
                                                         if k in ("displacement", "voltage", "force")),
                                 total=total, time_origin_ns=origin, **steps)
        print(_comparison_table(compare_models(run, fe_run), min(run.n_solves, fe_run.n_solves)))
    return 1 if run.failures else 0

"""Replaying recorded runs: the twin re-run on a bag's commands, republished live, plotted.

Bags are built here with :class:`Ros2McapWriter` from messages serialised by rclpy, the
way the twin's recorder writes them (every sequence filled, DESIGN.md section 4).
"""

import csv
import importlib.util
import math
import os
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest
import rclpy
from mcap_ros2.reader import read_ros2_messages
from rclpy.context import Context
from rclpy.executors import SingleThreadedExecutor
from rclpy.node import Node
from rclpy.qos import QoSProfile, ReliabilityPolicy
from rclpy.serialization import serialize_message
from sensor_msgs.msg import JointState
from std_msgs.msg import Float64MultiArray, MultiArrayDimension, String

from dea_array_twin import ArrayConfig, ArrayTwin, NewtonSettings
from dea_array_twin.bag.reader import Bag
from dea_array_twin.bag.series import load_series
from dea_array_twin.bag.twin_config import metadata_from_config
from dea_array_twin.bag.writer import Ros2McapWriter
from dea_array_twin.cli.main import main
from dea_array_twin.model.metrics import fit

REPO = Path(__file__).resolve().parents[2]
FLOATS, STATES, STRING = "std_msgs/msg/Float64MultiArray", "sensor_msgs/msg/JointState", "std_msgs/msg/String"
T0 = 1_700_000_000_000_000_000  # ns
MODES = ("driven", "driven", "free")
# (time after T0 [s], kind, values): small steps (<= 2 mm), some high voltage, two invalid commands
COMMANDS = [
    (0.10, "displacement", [0.0, 0.002, 0.0]),
    (0.20, "voltage", [0.0, 1500.0, 0.0]),
    (0.30, "displacement", [0.001, 0.004, 0.0]),
    (0.35, "displacement", [0.001, 0.004]),  # wrong length: skipped
    (0.40, "voltage", [1000.0, 2000.0, 0.0]),
    (0.50, "displacement", [0.002, 0.005, 0.0]),
    (0.55, "voltage", [0.0, math.nan, 0.0]),  # NaN: skipped
    (0.60, "displacement", [0.002, 0.003, 0.0]),
    (0.70, "voltage", [0.0, 0.0, 0.0]),
    (0.80, "displacement", [0.0, 0.001, 0.0]),
]


def ns(t: float) -> int:
    return T0 + int(round(t * 1e9))


def floats(values) -> Float64MultiArray:
    msg = Float64MultiArray(data=[float(v) for v in values])
    msg.layout.dim = [MultiArrayDimension(label="unit", size=len(msg.data), stride=len(msg.data))]
    return msg


def write_bag(path: Path, messages, metadata=None) -> Path:
    """``messages``: (topic, type, message, log time [ns]); written in the given order."""
    with Ros2McapWriter(path, metadata=metadata, flush_period=None) as rec:
        ids = {}
        for topic, type_name, msg, t in messages:
            if topic not in ids:
                ids[topic] = rec.add_topic(topic, type_name)
            rec.write(ids[topic], serialize_message(msg), t)
    return path


def twin_recording(path: Path, names=None, extra=(), with_config=True, error=None):
    """A bag like the twin node's recorder writes: commands, outputs 5 ms after each, config metadata.

    ``error(i, force, capacitance) -> (force, capacitance)`` changes the i-th recorded
    output (a "measurement" that differs from the model by a known amount).  Returns
    the path and the model's outputs ``[(t_ns, force, capacitance)]`` (before ``error``).
    """
    names = names or {"displacement": "/command/displacement", "voltage": "/command/voltage"}
    cfg = ArrayConfig()
    # Unchecked solves, as the replay makes them: a checked solve takes another Newton
    # path to the same equilibrium (within the solver tolerance, ~3e-8 N in force), and
    # the tests below compare replayed forces to 1e-9 N.
    twin = ArrayTwin(cfg, NewtonSettings(check_stability=False))
    held = {"displacement": np.zeros(3), "voltage": np.zeros(3)}
    res = twin.solve(held["displacement"], held["voltage"], MODES)
    outputs = [(ns(0.05), res.force, res.capacitance)]  # published before the first command
    messages = []
    for t, kind, values in COMMANDS:
        messages.append((names[kind], FLOATS, floats(values), ns(t)))
        if len(values) != 3 or not np.all(np.isfinite(values)):
            continue
        held[kind] = np.array(values)
        res = twin.solve(held["displacement"], held["voltage"], MODES)
        outputs.append((ns(t + 0.005), res.force, res.capacitance))
    for i, (t, force, cap) in enumerate(outputs):
        if error is not None:
            force, cap = error(i, np.array(force), np.array(cap))
        messages += [("/force", FLOATS, floats(force), t), ("/capacitance", FLOATS, floats(cap), t)]
        states = JointState(name=["unit_1", "unit_2", "unit_3"], position=[0.0] * 3, velocity=[0.0] * 3,
                            effort=[float(v) for v in force])
        messages.append(("/unit_states", STATES, states, t))
    messages += list(extra)
    messages.sort(key=lambda m: m[3])
    # update_rate 0: the outputs answer each command at once
    metadata = {"dea_array_twin_config": metadata_from_config(cfg, MODES, 0.0)} if with_config else None
    write_bag(path, messages, metadata)
    return path, outputs


def read_topic(path: Path, topic: str):
    return [(m.log_time_ns, list(m.ros_msg.data) if hasattr(m.ros_msg, "data") else m.ros_msg)
            for m in read_ros2_messages(str(path), topics=[topic])]


# -------------------------------------------------------------------------- FIT

def test_fit_is_100_for_a_perfect_model_0_for_the_mean_and_follows_eq_12():
    x = np.array([1.0, 2.0, 3.0, 4.0])
    assert fit(x, x) == 100.0
    assert fit(x, np.full(4, 2.5)) == pytest.approx(0.0, abs=1e-12)
    # ||x - xm|| = 1, ||x - mean x|| = sqrt(1.5^2 + 0.5^2 + 0.5^2 + 1.5^2) = sqrt(5)
    assert fit(x, [1.0, 2.0, 3.0, 5.0]) == pytest.approx(100 * (1 - 1 / math.sqrt(5)), rel=1e-12)
    assert fit(x, -x) < 0.0  # worse than the mean


def test_fit_of_a_constant_measured_signal_is_nan():
    with np.errstate(all="raise"):  # no division warning either
        assert math.isnan(fit([0.0, 0.0, 0.0], [0.0, 0.1, 0.0]))
        assert math.isnan(fit([2.0], [1.0]))  # one sample has no spread
        assert math.isnan(fit([0.1] * 7, [0.1] * 7))
        assert math.isnan(fit([], []))
    with pytest.raises(ValueError, match="same shape"):
        fit([1.0, 2.0], [1.0])


# ----------------------------------------------------------------- offline replay

def test_replay_of_a_twin_recording_reproduces_its_outputs(tmp_path, capsys):
    bag, outputs = twin_recording(tmp_path / "run.mcap")
    assert main(["replay", str(bag)]) == 0
    out, err = capsys.readouterr()
    assert "config from the bag" in err and "unit modes driven, driven, free from the bag's metadata" in err
    assert "skipped 1 invalid displacement" in err and "skipped 1 invalid voltage" in err

    # FIT table: every unit and channel, the free unit's constant zero force is n/a
    lines = [line.split() for line in out.splitlines() if line.strip()[:1].isdigit()]
    table = {int(row[0]): row[1:] for row in lines if len(row) == 3}
    assert sorted(table) == [1, 2, 3]
    for unit, (f_fit, c_fit) in table.items():
        assert float(c_fit) > 99.99
        if unit == 3:
            assert f_fit == "n/a"
        else:
            assert float(f_fit) > 99.99

    # the MCAP: one force/capacitance/unit_states per accepted command, at the command's log time
    out_mcap, out_csv = tmp_path / "run_replay.mcap", tmp_path / "run_replay.csv"
    valid = [(ns(t), kind, v) for t, kind, v in COMMANDS if len(v) == 3 and np.all(np.isfinite(v))]
    forces = read_topic(out_mcap, "/force")
    caps = read_topic(out_mcap, "/capacitance")
    assert [t for t, _ in forces] == [t for t, _, _ in valid] == [t for t, _ in caps]
    for (_, force), (_, cap), (_, f_ref, c_ref) in zip(forces, caps, outputs[1:]):
        np.testing.assert_allclose(force, f_ref, rtol=1e-6, atol=1e-9)
        np.testing.assert_allclose(cap, c_ref, rtol=1e-6)
    states = [m.ros_msg for m in read_ros2_messages(str(out_mcap), topics=["/unit_states"])]
    assert len(states) == len(valid) and list(states[-1].name) == ["unit_1", "unit_2", "unit_3"]
    np.testing.assert_allclose(states[-1].effort, forces[-1][1])
    assert [v for _, v in read_topic(out_mcap, "/command/voltage")][-1] == [0.0, 0.0, 0.0]

    # the CSV: header, one row per solve, time from the bag's first message, SI values
    with open(out_csv, newline="") as f:
        rows = list(csv.reader(f))
    assert rows[0] == ["time_s", "d1_m", "d2_m", "d3_m", "V1_V", "V2_V", "V3_V", "F1_N", "F2_N", "F3_N",
                       "C1_F", "C2_F", "C3_F"]
    data = np.array(rows[1:], dtype=float)
    assert data.shape == (len(valid), 13)
    np.testing.assert_allclose(data[:, 0], [(t - ns(0.05)) * 1e-9 for t, _, _ in valid], atol=1e-9)
    np.testing.assert_allclose(data[3], [0.35, 0.001, 0.004, 0.0, 1000, 2000, 0] + list(outputs[4][1])
                               + list(outputs[4][2]), rtol=1e-6, atol=1e-9)

    # the output is itself a replayable bag: its recorded config and commands give the same outputs
    assert main(["replay", str(out_mcap), "--out", str(tmp_path / "again")]) == 0
    again = np.loadtxt(tmp_path / "again.csv", delimiter=",", skiprows=1)
    np.testing.assert_allclose(again[:, 1:], data[:, 1:], rtol=1e-6, atol=1e-9)


def _fit_table(out: str) -> dict[int, list[str]]:
    """The printed FIT table: unit -> [force FIT, capacitance FIT] as printed."""
    rows = [line.split() for line in out.splitlines() if line.strip()[:1].isdigit()]
    return {int(row[0]): row[1:] for row in rows if len(row) == 3}


def test_replay_fit_of_outputs_off_by_a_known_error_is_what_eq_12_gives(tmp_path, capsys):
    """Recorded outputs = model + a known error e, so eq. 12 gives FIT = 100 (1 - ||e|| /
    ||x - mean x||) for the recorded series x: the printed FIT must be that, not 100."""
    rng = np.random.default_rng(3)
    errors = {}

    def error(i, force, cap):
        e_f = rng.normal(0.0, 2e-3, 3) * [1, 1, 0]  # N; the free unit 3 stays at 0 force
        e_c = rng.normal(0.0, 0.5e-12, 3)  # F
        errors[i] = (e_f, e_c)
        return force + e_f, cap + e_c

    bag, outputs = twin_recording(tmp_path / "noisy.mcap", error=error)
    assert main(["replay", str(bag)]) == 0
    table = _fit_table(capsys.readouterr().out)
    for kind, col in (("force", 0), ("capacitance", 1)):
        for unit in (1, 2) if kind == "force" else (1, 2, 3):
            k = unit - 1
            model = np.array([o[1 + col][k] for o in outputs])
            e = np.array([errors[i][col][k] for i in range(len(outputs))])
            x = model + e
            expected = 100.0 * (1.0 - np.linalg.norm(e) / np.linalg.norm(x - x.mean()))
            assert expected < 99.5  # not a perfect fit: the recording differs from the model
            # the replay reproduces the model to ~1e-6 relative: 0.01 points is generous
            assert float(table[unit][col]) == pytest.approx(expected, abs=1e-2), (kind, unit)


def _ramp_run(n_states: int, step_ns: int):
    """A replay of a ramp: state j (force j, capacitance 10 j) current from j * step_ns on."""
    from dea_array_twin.replay.offline import ReplayRun

    values = np.arange(1.0, n_states + 1.0)[:, None] * np.ones((1, 2))
    return ReplayRun(times_ns=np.arange(1, n_states + 1, dtype=np.int64) * step_ns,
                     kinds=["displacement"] * n_states, displacement=values, voltage=values, force=values,
                     capacitance=10 * values, centre_deflection=values, initial_force=np.zeros(2),
                     initial_capacitance=np.zeros(2))


def test_fit_lag_window_pairs_late_outputs_but_reaches_no_further_than_the_lag():
    """Outputs that lag their states by 2 steps: a window of 2 steps pairs them exactly
    (FIT 100); a window of 1 step pairs each with the state 1 step later than its own,
    which eq. 12 scores exactly; no window makes a signal unrelated to the states fit."""
    from dea_array_twin.replay.offline import compare_outputs

    step = 10_000_000  # 10 ms between states
    run = _ramp_run(40, step)
    states = np.vstack([np.zeros((1, 2)), run.force])  # state j current from j * step on
    j = np.arange(3, 41)
    times = (j * step + step // 2).astype(np.int64)  # the output at (j + 0.5) step shows state j - 2
    late = states[j - 2]
    recorded = {"force": (times, late)}
    expected_0 = fit(late[:, 0], states[j, 0])
    assert 50.0 < expected_0 < 99.0
    np.testing.assert_allclose(compare_outputs(run, recorded, lag_ns=0)["force"], expected_0, atol=1e-12)
    assert np.all(compare_outputs(run, recorded, lag_ns=2 * step)["force"] == 100.0)
    np.testing.assert_allclose(compare_outputs(run, recorded, lag_ns=step)["force"],
                               fit(late[:, 0], states[j - 1, 0]), atol=1e-12)
    # Late by one step in a window of three: the pairing picks the state that fits,
    # not the oldest or the newest candidate, unit by unit the same state.
    one_late = states[j - 1] * [1.0, 2.0]
    run.force[:, 1] *= 2.0
    assert np.all(compare_outputs(run, {"force": (times, one_late)}, lag_ns=3 * step)["force"] == 100.0)
    run.force[:, 1] /= 2.0
    # A recorded output logged at the very instant of its command (as an offline replay
    # writes them) shows the new state.
    at_command = (j * step).astype(np.int64)
    assert np.all(compare_outputs(run, {"force": (at_command, states[j])}, lag_ns=0)["force"] == 100.0)
    # The window is (t - lag, t]: a state replaced exactly at t - lag is no candidate.
    three_late = states[j - 3]
    np.testing.assert_allclose(compare_outputs(run, {"force": (at_command, three_late)}, lag_ns=2 * step)["force"],
                               fit(three_late[:, 0], states[j - 2, 0]), atol=1e-12)
    # A signal unrelated to the states (alternating far above and below them) gets no
    # better than pairing it with its current state gives, whatever the window.
    unrelated = states[j] + np.where(np.arange(j.size) % 2, 50.0, -50.0)[:, None]
    honest = fit(unrelated[:, 0], states[j, 0])
    assert honest < 5.0
    for lag in (0, step, 5 * step):
        assert compare_outputs(run, {"force": (times, unrelated)}, lag_ns=lag)["force"][0] < honest + 10.0


def test_a_command_without_equilibrium_is_reported_and_the_replay_goes_on_like_the_node(tmp_path, capsys,
                                                                                      monkeypatch):
    """The node keeps its last state at a failed solve, holds the command and goes on: so does the replay,
    and exits 1 at the end."""
    from dea_array_twin.model.solver import ConvergenceError

    bag, outputs = twin_recording(tmp_path / "run.mcap")
    solve = ArrayTwin.solve
    calls = []

    def failing_solve(self, *args, **kwargs):
        calls.append(args)
        if len(calls) == 5:  # the zero state and three commands solve, the fourth command fails
            raise ConvergenceError("no equilibrium (injected)")
        return solve(self, *args, **kwargs)

    monkeypatch.setattr(ArrayTwin, "solve", failing_solve)
    assert main(["replay", str(bag)]) == 1
    err = capsys.readouterr().err
    assert "keeping the last state" in err and "injected" in err and "t = 0.350000 s" in err
    assert "1 command(s) without equilibrium" in err and "Traceback" not in err
    forces = read_topic(tmp_path / "run_replay.mcap", "/force")
    assert len(forces) == len(outputs) - 2  # every solve but the failed one (outputs[0] is the zero state)
    # the failed voltage stays held: the next command solves with it, as the recording did
    for (t, force), (t_rec, recorded, _) in zip(forces[3:], outputs[5:]):
        np.testing.assert_allclose(force, recorded, rtol=1e-6, atol=1e-9)
    assert len((tmp_path / "run_replay.csv").read_text().splitlines()) == 1 + len(outputs) - 2


def test_replay_maps_renamed_command_topics_and_ignores_others(tmp_path, capsys):
    names = {"displacement": "/rig/disp", "voltage": "/rig/hv"}
    extra = [("/rig/status", STRING, String(data="ok"), ns(0.15)),
             ("/other/force_sensor", FLOATS, floats([9.0, 9.0]), ns(0.25))]
    bag, outputs = twin_recording(tmp_path / "rig.mcap", names=names, extra=extra, with_config=False)
    assert main(["replay", str(bag)]) == 2  # nothing ends with command/...
    err = capsys.readouterr().err
    assert "no command topics" in err and "/rig/disp" in err and "/rig/status" in err

    out_base = tmp_path / "mapped"
    assert main(["replay", str(bag), "--modes", "driven,driven,free", "--out", str(out_base),
                 "--topic-map", "/rig/disp=command/displacement", "rig/hv=command/voltage"]) == 0
    out, err = capsys.readouterr()
    assert "default ArrayConfig" in err and "from --modes" in err and "/rig/disp" in err
    forces = read_topic(out_base.with_suffix(".mcap"), "/force")
    assert len(forces) == len(outputs) - 1
    np.testing.assert_allclose(forces[-1][1], outputs[-1][1], rtol=1e-6, atol=1e-9)
    assert "FIT" in out  # the recorded /force is compared


def test_replay_without_command_topics_exits_2_listing_the_topics(tmp_path, capsys):
    bag = write_bag(tmp_path / "none.mcap", [("/chatter", STRING, String(data="hi"), ns(0.1)),
                                             ("/force", FLOATS, floats([1.0, 2.0, 3.0]), ns(0.2))])
    assert main(["replay", str(bag)]) == 2
    err = capsys.readouterr().err
    assert "no command topics" in err and "/chatter" in err and "std_msgs/msg/String" in err
    assert "Traceback" not in err
    assert not (tmp_path / "none_replay.mcap").exists()


def test_truncated_and_non_mcap_inputs_exit_2_with_a_clear_error(tmp_path, capsys):
    bag, _ = twin_recording(tmp_path / "whole.mcap")
    cut = tmp_path / "cut.mcap"
    raw = bag.read_bytes()
    cut.write_bytes(raw[: len(raw) // 2])
    assert main(["replay", str(cut)]) == 2
    err = capsys.readouterr().err
    assert "cut off" in err and "python -m dea_array_twin.bag.recover" in err and "Traceback" not in err

    text = tmp_path / "notes.mcap"
    text.write_text("these are not the messages you are looking for\n")
    assert main(["replay", str(text)]) == 2
    err = capsys.readouterr().err
    assert "not an MCAP file" in err and "Traceback" not in err

    assert main(["replay", str(tmp_path / "missing.mcap")]) == 2
    assert "no such file" in capsys.readouterr().err
    if importlib.util.find_spec("matplotlib"):
        assert main(["plot", str(cut), "-o", str(tmp_path / "x.png")]) == 2
        assert "dea_array_twin.bag.recover" in capsys.readouterr().err


def test_replay_of_a_rosbag2_directory_reads_its_files_in_order(tmp_path, capsys):
    # a directory bag split in two files, each with its own copy of the metadata
    bag, _ = twin_recording(tmp_path / "single.mcap")
    assert main(["replay", str(bag), "--out", str(tmp_path / "single_out")]) == 0
    folder = tmp_path / "split_bag"
    folder.mkdir()
    from dea_array_twin.bag.reader import Bag

    whole = Bag(bag)
    meta = {"dea_array_twin_config": whole.metadata("dea_array_twin_config")}
    msgs = list(whole.messages(whole.topics, decode=False))
    half = len(msgs) // 2
    for i, part in enumerate((msgs[:half], msgs[half:])):
        with Ros2McapWriter(folder / f"split_bag_{i}.mcap", metadata=meta, flush_period=None) as rec:
            ids = {}
            for m in part:
                ids.setdefault(m.topic, rec.add_topic(m.topic, m.type_name))
                rec.write(ids[m.topic], m.data, m.log_time_ns)
    (folder / "metadata.yaml").write_text(
        "rosbag2_bagfile_information:\n  storage_identifier: mcap\n"
        "  relative_file_paths:\n  - split_bag_0.mcap\n  - split_bag_1.mcap\n")
    assert main(["replay", str(folder)]) == 0
    capsys.readouterr()
    a = np.loadtxt(tmp_path / "single_out.csv", delimiter=",", skiprows=1)
    b = np.loadtxt(tmp_path / "split_bag_replay.csv", delimiter=",", skiprows=1)
    np.testing.assert_allclose(b, a, rtol=1e-9, atol=1e-12)

    # a folder of several recordings (no metadata.yaml) is refused rather than merged
    (folder / "metadata.yaml").unlink()
    (folder / "split_bag_1.mcap").rename(folder / "other_run.mcap")
    assert main(["replay", str(folder)]) == 2
    assert "holds 2 recordings" in capsys.readouterr().err


# ----------------------------------------------------------------------- plot

def test_plot_writes_a_png_of_a_recording_and_of_a_replay(tmp_path, capsys):
    pytest.importorskip("matplotlib")
    bag, _ = twin_recording(tmp_path / "run.mcap")
    png = tmp_path / "run.png"
    assert main(["plot", str(bag), "-o", str(png)]) == 0
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n" and png.stat().st_size > 10_000
    assert main(["replay", str(bag)]) == 0
    assert main(["plot", str(tmp_path / "run_replay.mcap")]) == 0  # default name: next to the bag
    assert (tmp_path / "run_replay.png").stat().st_size > 10_000
    # What was drawn: the replay's forces at the replay's times, as its CSV holds them.
    series, _ = load_series(Bag(tmp_path / "run_replay.mcap"))
    with open(tmp_path / "run_replay.csv") as f:
        rows = list(csv.DictReader(f))
    np.testing.assert_allclose(series["force"].time_s, [float(r["time_s"]) for r in rows], atol=1e-9)
    np.testing.assert_allclose(series["force"].values, [[float(r[f"F{k}_N"]) for k in (1, 2, 3)] for r in rows])
    capsys.readouterr()


# ------------------------------------------------------------- realtime replay

def test_realtime_replay_republishes_commands_in_order_with_scaled_timing(tmp_path, monkeypatch):
    from domain_coordinator import domain_id

    spacing, count, rate = 0.4, 8, 2.0  # 2.8 s of recording -> 1.4 s at 2x
    messages = []
    for i in range(count):
        messages.append(("/command/displacement", FLOATS, floats([0.0, 1e-4 * i, 0.0]), ns(i * spacing)))
        messages.append(("/command/voltage", FLOATS, floats([0.0, 100.0 * i, 0.0]), ns(i * spacing + 0.2)))
    bag = write_bag(tmp_path / "commands.mcap", messages)

    received = {}
    lock = threading.Lock()

    def store(key, msg):
        with lock:
            received.setdefault(key, []).append((time.monotonic(), list(msg.data)))

    with domain_id() as domain:
        monkeypatch.setenv("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")
        context = Context()
        rclpy.init(context=context, domain_id=domain)
        node = Node("replay_listener", context=context)
        for topic in ("command/displacement", "command/voltage"):  # listening before replay starts
            for name, reliability in (("best_effort", ReliabilityPolicy.BEST_EFFORT),
                                      ("reliable", ReliabilityPolicy.RELIABLE)):
                node.create_subscription(Float64MultiArray, topic, lambda m, k=(topic, name): store(k, m),
                                         QoSProfile(depth=100, reliability=reliability))
        executor = SingleThreadedExecutor(context=context)
        executor.add_node(node)

        def spin():
            while context.ok():
                executor.spin_once(timeout_sec=0.05)

        spinner = threading.Thread(target=spin, daemon=True)
        spinner.start()
        try:
            env = dict(os.environ, ROS_DOMAIN_ID=str(domain), ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST")
            proc = subprocess.run([sys.executable, "-m", "dea_array_twin.cli.main", "replay", "--realtime", str(bag),
                                   "--rate", str(rate), "--wait", "10"],
                                  env=env, capture_output=True, text=True, timeout=60, cwd=REPO)
            assert proc.returncode == 0, proc.stderr
            assert f"published {2 * count} message(s)" in proc.stderr
            deadline = time.monotonic() + 5.0
            while time.monotonic() < deadline:
                with lock:
                    if all(len(received.get((t, q), [])) == count for t in ("command/displacement", "command/voltage")
                           for q in ("best_effort", "reliable")):
                        break
                time.sleep(0.05)
        finally:
            executor.shutdown()
            context.try_shutdown()
            spinner.join(timeout=5.0)
            node.destroy_node()

    for qos in ("best_effort", "reliable"):
        disp = received.get(("command/displacement", qos), [])
        volt = received.get(("command/voltage", qos), [])
        assert [v[1] for _, v in disp] == pytest.approx([1e-4 * i for i in range(count)]), qos
        assert [v[1] for _, v in volt] == pytest.approx([100.0 * i for i in range(count)]), qos
        # Scaled timing: a message every spacing / rate = 0.2 s on each topic, the span 1.4 s.
        # Arrival times carry the transport's latency, which a loaded machine stretches
        # now and then: medians and a span bounded mostly from below (the replay may run
        # late, never early) keep the test about the schedule, not the scheduler.
        gap = spacing / rate
        span = disp[-1][0] - disp[0][0]
        assert (count - 1) * gap - 0.15 < span < (count - 1) * gap + 1.0, qos
        assert np.median(np.diff([t for t, _ in disp])) == pytest.approx(gap, abs=0.05), qos
        # voltage 0.2 s after each displacement in the bag -> 0.1 s
        offsets = [tv - td for (td, _), (tv, _) in zip(disp, volt)]
        assert np.median(offsets) == pytest.approx(0.2 / rate, abs=0.05), (qos, offsets)


def test_the_default_fit_lag_covers_the_longest_solve_the_recording_node_reported(tmp_path):
    """At 50 Hz three periods are 60 ms; a node whose diagnostics report a 200 ms solve answered up to
    one period + 200 ms late, so that is the window (a bag without the twin's metadata: 0)."""
    from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue

    from dea_array_twin.replay.offline import default_fit_lag

    def diagnostics(solve_max_ms: str) -> DiagnosticArray:
        status = DiagnosticStatus(name="twin", message="ok", hardware_id="dea_array_twin",
                                  values=[KeyValue(key="solve_time_max_ms", value=solve_max_ms)])
        return DiagnosticArray(status=[status])

    meta = {"dea_array_twin_config": metadata_from_config(ArrayConfig(), MODES, 50.0)}
    diag_type = "diagnostic_msgs/msg/DiagnosticArray"
    quick = write_bag(tmp_path / "quick.mcap", [("/diagnostics", diag_type, diagnostics("12.5"), T0)], meta)
    assert default_fit_lag(Bag(quick)) == (pytest.approx(0.06), "three update periods of the recording node")
    slow = write_bag(tmp_path / "slow.mcap", [("/diagnostics", diag_type, diagnostics(v), T0 + i)
                                              for i, v in enumerate(["12.5", "200.0", "nan"])], meta)
    lag, why = default_fit_lag(Bag(slow))
    assert lag == pytest.approx(0.02 + 0.2) and "200.0 ms" in why
    plain = write_bag(tmp_path / "plain.mcap", [("/diagnostics", diag_type, diagnostics("200.0"), T0)])
    assert default_fit_lag(Bag(plain))[0] == 0.0

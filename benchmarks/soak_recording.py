"""Soak of the recording twin node: random valid commands for a while, then count what the bag holds.

Run:  .venv/bin/python benchmarks/soak_recording.py [--duration 600] [--update-rate 100]
          [--command-rate 100] [--coarse] [--slow-every 0]

The twin runs as a separate process (as under ``ros2 run``) with ``record:=true`` on a
free ROS domain; this process publishes both commands at ``--command-rate`` each
(random displacements of every unit in [0, 10] mm and voltages in [0, 2000] V, the run
that kept 35 % of its commands before the solver left the executor; ``--slow-every N``
makes every Nth voltage command one beyond electromechanical stability, accepted by a
raised ``breakdown_field``, where Newton fails slowly).  Reports:

* commands sent and commands in the bag, per topic; the recorder's dropped count;
* the largest gaps between consecutive outputs and diagnostics received here, and
  between their log times in the bag (received inside the node's process by its
  recorder: this process's own stalls do not count there; the gaps between the
  recorded commands show those stalls of the sender);
* solve time p50 / p95 / max as the node's diagnostics report them (over 10 s windows:
  the median of the p50s, the largest p95 and max), budget overruns, skipped ticks;
* the output latency of the node: for each displacement command, the time from its
  receipt (bag log time) to the first ``unit_states`` whose driven positions equal it,
  p50 / p95 / max (commands superseded before they were solved are not answered);
* the load (``os.getloadavg``) before and after.

Not a test: numbers for the notes.
"""

from __future__ import annotations

import argparse
import bisect
import os
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
from mcap_ros2.reader import read_ros2_messages

from dea_array_twin.ros.testing import TwinHarness, diagnostic_values

COARSE = {"mesh_size": 20e-3, "mesh_size_indenter": 2.5e-3, "mesh_size_electrode": 5e-3}


def _gap(times: list[float], start: float, end: float) -> float:
    inside = [t for t in times if start <= t <= end]
    return float(np.diff(inside).max()) if len(inside) > 1 else float("nan")


def soak(duration: float, update_rate: float, command_rate: float, coarse: bool, slow_every: int) -> dict:
    folder = Path(tempfile.mkdtemp(prefix="soak_"))
    params = {"update_rate": update_rate, "record": True, "record_dir": str(folder), "marker_rate": 5.0}
    if coarse:
        params.update(COARSE)
    if slow_every:
        params["breakdown_field"] = 300e6
    rng = np.random.default_rng(1)
    load_before = os.getloadavg()
    with TwinHarness(parameters=params, process=True) as h:
        h.wait_for("force", timeout=60)
        start, k, period = time.monotonic(), 0, 1.0 / command_rate
        last_report = start
        while time.monotonic() - start < duration:
            h.send_displacement(rng.uniform(0.0, 0.010, 3))
            slow = slow_every and k % slow_every == slow_every - 1
            h.send_voltage([0.0, 10000.0, 0.0] if slow else rng.uniform(0.0, 2000.0, 3))
            k += 1
            if time.monotonic() - last_report > 30:
                last_report = time.monotonic()
                print(f"  {last_report - start:5.0f} s: {k} command pairs sent", file=sys.stderr, flush=True)
            time.sleep(max(0.0, start + k * period - time.monotonic()))
        end = time.monotonic()
        time.sleep(2.0)
        diagnostics = [diagnostic_values(m) for m in h.messages("/diagnostics")]
        gaps = {name: _gap(h.receive_times(name), start, end) for name in ("force", "unit_states", "/diagnostics")}
        sent = dict(h.sent)
    bag = next(folder.glob("*.mcap"))
    run = {
        "duration_s": duration, "update_rate_hz": update_rate, "command_rate_hz": command_rate,
        "mesh": "coarse" if coarse else "default", "bag": str(bag), "sent": sent, "max_gap_s": gaps,
        "load_before": load_before, "load_after": os.getloadavg(),
    }
    for key, value in run.items():  # before the bag is read (which takes a while)
        print(f"{key}: {value}", flush=True)
    return {**run, **analyse(bag, diagnostics)}


def analyse(bag: Path, diagnostics: list[dict]) -> dict:
    """Message counts of the bag, the node's solve statistics and its output latency."""
    from mcap.reader import make_reader

    with open(bag, "rb") as f:
        summary = make_reader(f).get_summary()
    topics = {c.id: c.topic for c in summary.channels.values()}
    counts = {topics[k]: v for k, v in summary.statistics.channel_message_counts.items()}
    commands, states = [], []
    for m in read_ros2_messages(str(bag), topics=["/command/displacement", "/unit_states"]):
        target = commands if m.channel.topic == "/command/displacement" else states
        target.append((m.log_time_ns, tuple(m.ros_msg.data if target is commands else m.ros_msg.position)))
    logged: dict[str, list[int]] = {}
    with open(bag, "rb") as f:
        for _, channel, message in make_reader(f).iter_messages(topics=["/force", "/diagnostics",
                                                                          "/command/displacement"]):
            logged.setdefault(channel.topic, []).append(message.log_time)
    final = diagnostics[-1]
    p50s = [float(d["solve_time_p50_ms"]) for d in diagnostics if d.get("solve_time_p50_ms", "nan") != "nan"]
    return {
        "in_bag": {"displacement": counts.get("/command/displacement", 0),
                   "voltage": counts.get("/command/voltage", 0)},
        "outputs_in_bag": counts.get("/force", 0), "recorder_dropped": final.get("recorder_dropped"),
        "max_gap_in_bag_s": {topic: float(np.diff(times).max()) * 1e-9 for topic, times in logged.items()},
        "solve_ms": {"p50 (median of windows)": float(np.median(p50s)) if p50s else float("nan"),
                     "p95 (largest)": max(float(d.get("solve_time_p95_ms", "nan")) for d in diagnostics),
                     "max": max(float(d.get("solve_time_max_ms", "nan")) for d in diagnostics)},
        "updates": final["updates"], "budget_overruns": final["budget_overruns"],
        "failed_solves": final["failed_solves"], "skipped_ticks": final["skipped_ticks"],
        "output_latency_ms": _latencies(commands, states),
    }


def _latencies(commands: list, states: list) -> dict:
    """Receipt of each displacement command to the first unit_states showing it (ms), p50/p95/max.

    Driven units report exactly the commanded displacement, so a command is answered by the
    first later state whose positions equal its values.
    """
    shown: dict[tuple, list[int]] = {}
    for t, values in states:
        shown.setdefault(values, []).append(t)
    out = []
    for t, values in commands:
        times = shown.get(values, [])
        i = bisect.bisect_left(times, t)
        if i < len(times):
            out.append((times[i] - t) * 1e-6)
    arr = np.array(out)
    if not arr.size:
        return {"answered": 0, "of": len(commands)}
    return {"answered": int(arr.size), "of": len(commands), "p50": float(np.percentile(arr, 50)),
            "p95": float(np.percentile(arr, 95)), "max": float(arr.max())}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--duration", type=float, default=600.0, help="seconds of commands (default 600)")
    parser.add_argument("--update-rate", type=float, default=100.0, help="the node's update_rate [Hz]")
    parser.add_argument("--command-rate", type=float, default=100.0, help="commands per second per kind")
    parser.add_argument("--coarse", action="store_true", help="the coarse test mesh instead of the default")
    parser.add_argument("--slow-every", type=int, default=0, help="every Nth voltage command fails slowly")
    args = parser.parse_args()
    result = soak(args.duration, args.update_rate, args.command_rate, args.coarse, args.slow_every)
    for key in ("in_bag", "outputs_in_bag", "recorder_dropped", "max_gap_in_bag_s", "solve_ms", "updates",
                "budget_overruns", "failed_solves", "skipped_ticks", "output_latency_ms"):
        print(f"{key}: {result[key]}")


if __name__ == "__main__":
    main()

"""The cooperative wave: a neighbour's capacitance rise passes the deflection on.

The rule (:class:`Wave`) is tested with synthetic capacitances, the node
(:class:`WaveController`) against the twin over DDS.
"""

import math
import time

import numpy as np
import pytest
from rclpy.parameter import Parameter

from dea_array_twin import ArrayTwin
from dea_array_twin.ros.wave_controller import Wave, WaveController, WaveSettings

A = 0.006  # amplitude [m]
RATE = 20  # updates per second; times k / RATE are exact in binary for the checks below


def coupled_capacitance(command, c0, self_gain=0.06, neighbour_gain=0.006):
    """Synthetic self-sensing: a unit's capacitance rises with its own deflection and,
    less, with its row neighbours' (about what the twin gives at 6 mm)."""
    d = np.asarray(command) / A
    padded = np.pad(d, 1)
    return np.asarray(c0) * (1 + self_gain * d**2 + neighbour_gain * (padded[:-2] ** 2 + padded[2:] ** 2))


def run(wave, seconds, capacitance=None, c0=2.28e-10):
    """Drive ``wave`` at RATE for ``seconds``; capacitance(t, last_command) or the coupled plant."""
    c0 = np.broadcast_to(c0, (wave.n_units,))
    command = np.zeros(wave.n_units)
    times, commands, events = [], [], []
    for k in range(int(seconds * RATE) + 1):
        t = k / RATE
        cap = capacitance(t, command) if capacitance else coupled_capacitance(command, c0)
        command = wave.update(t, cap)
        times.append(t)
        commands.append(command)
        events += wave.pop_events()
    return np.array(times), np.array(commands), events


def units_reaching_amplitude(commands):
    """Units in the order they arrive at the amplitude (one entry per arrival)."""
    at = commands >= A - 1e-12
    arrivals = at[1:] & ~at[:-1]
    return [int(u) for step in arrivals for u in np.flatnonzero(step)]


def test_next_unit_waits_until_its_own_capacitance_rose_by_the_trigger_fraction():
    c0 = np.array([2.0e-10, 3.0e-10, 2.5e-10])  # each unit's rise is relative to its own baseline
    rise_of_unit_2 = {"value": 0.0}

    def capacitance(t, command):
        return c0 * np.array([1.0, 1.0 + rise_of_unit_2["value"], 1.0])

    wave = Wave(3, WaveSettings(amplitude=A, ramp_time=1.0, trigger_fraction=0.002, settle_time=0.5))
    times, commands, events = run(wave, 5.0, capacitance)
    assert [e.kind for e in events] == ["baseline"]
    assert np.all(commands[times < 0.5 + 1e-9] == 0.0)  # settling at 0 m
    assert commands[-1, 0] == pytest.approx(A) and np.all(commands[:, 1:] == 0.0)  # holding, no trigger
    ramp = commands[(times >= 0.5) & (times <= 1.5), 0]
    assert np.all(np.diff(ramp) > 0) and ramp[-1] == pytest.approx(A)

    rise_of_unit_2["value"] = 0.001  # +0.1 % (0.3e-12 F): below +0.2 %
    assert np.all(wave.update(6.0, capacitance(6.0, None)) == [A, 0.0, 0.0])
    assert wave.waiting_since == pytest.approx(1.5)
    rise_of_unit_2["value"] = 0.003
    assert np.all(wave.update(6.05, capacitance(6.05, None)) == [A, 0.0, 0.0])  # ramps start here
    command = wave.update(6.3, capacitance(6.3, None))
    assert command[0] == pytest.approx(0.75 * A) and command[1] == pytest.approx(0.25 * A) and command[2] == 0
    (event,) = wave.pop_events()
    assert (event.kind, event.unit, event.time) == ("triggered", 1, 6.05)
    assert event.rise == pytest.approx(0.003)
    assert "unit 2 triggered by capacitance +0.30 %" in event.describe()


def test_capacitance_rise_passes_the_wave_on_only_once_the_unit_reached_amplitude():
    def capacitance(t, command):  # the neighbour reads +1 % as soon as the baseline is taken
        return np.array([1.0, 1.01 if t > 0.5 else 1.0, 1.0]) * 2.28e-10

    wave = Wave(3, WaveSettings(amplitude=A, ramp_time=1.0, settle_time=0.5))
    times, commands, events = run(wave, 1.6, capacitance)
    assert np.all(commands[times < 1.5, 1] == 0.0)
    assert commands[times < 1.5, 0].max() < A
    (trigger,) = [e for e in events if e.kind == "triggered"]
    assert (trigger.unit, trigger.time) == (1, 1.5)  # the first update at amplitude


def test_wave_visits_the_units_in_order_and_wraps_to_unit_1():
    wave = Wave(3, WaveSettings(amplitude=A, ramp_time=0.5, settle_time=0.25))
    times, commands, events = run(wave, 12.0)
    order = units_reaching_amplitude(commands)
    assert len(order) >= 7 and order == [k % 3 for k in range(len(order))]
    assert np.all((commands >= 0) & (commands <= A))
    assert np.all(np.count_nonzero(commands, axis=1) <= 2)  # one unit up, at most one on its way down
    kinds = [e.kind for e in events]
    assert "wrap" in kinds and "done" not in kinds and not wave.done
    assert [e.unit for e in events if e.kind == "wrap"] == [0] * kinds.count("wrap")


def test_wave_stops_at_zero_after_the_requested_cycles():
    wave = Wave(3, WaveSettings(amplitude=A, ramp_time=0.5, settle_time=0.25, cycles=2))
    times, commands, events = run(wave, 15.0)
    assert units_reaching_amplitude(commands) == [0, 1, 2, 0, 1, 2]
    assert wave.done and wave.cycle == 2
    assert [e.kind for e in events][-3:] == ["triggered", "cycle", "done"]
    done_at = events[-1].time
    assert np.all(commands[times >= done_at] == 0.0)


@pytest.mark.parametrize("n_units", [1, 2, 5])
def test_wave_runs_on_any_number_of_units(n_units):
    wave = Wave(n_units, WaveSettings(amplitude=A, ramp_time=0.5, settle_time=0.25, cycles=2))
    times, commands, events = run(wave, 4.0 * n_units + 2.0)
    assert units_reaching_amplitude(commands) == list(range(n_units)) * 2
    assert wave.done and np.all(commands[-1] == 0.0)


@pytest.mark.parametrize("changes", [{"amplitude": 0.0}, {"ramp_time": -1.0}, {"trigger_fraction": math.nan},
                                     {"cycles": -1}, {"cycles": 1.5}, {"settle_time": -0.1}])
def test_meaningless_wave_settings_are_refused_naming_the_field(changes):
    with pytest.raises(ValueError, match=next(iter(changes))):
        WaveSettings(**changes)


def test_wave_controller_deflects_twin_units_one_after_another_by_capacitance_trigger():
    from dea_array_twin.ros.testing import TwinHarness

    with TwinHarness(parameters={"update_rate": 50.0}) as h:
        controller = WaveController(context=h.context, parameter_overrides=[  # an integer rate, as -p rate:=20
            Parameter("rate", value=20), Parameter("ramp_time", value=0.5), Parameter("amplitude", value=A),
            Parameter("cycles", value=1)])
        h.executor.add_node(controller)
        try:
            deadline = time.monotonic() + 40.0
            while not (controller.wave and controller.wave.done) and time.monotonic() < deadline:
                time.sleep(0.05)
            assert h.spin_error is None, h.spin_error
            assert controller.wave and controller.wave.done, "the wave did not finish in 40 s"
            # cycles = 1: the wave ends with every unit back at 0 m
            h.wait_for("unit_states", lambda m: max(abs(p) for p in m.position) < 1e-9, timeout=10.0,
                       after=len(h.messages("unit_states")) - 1)
            states = h.messages("unit_states")
            positions = np.array([m.position for m in states])
            # Each unit's command sits at A for about one control period before the next unit's
            # trigger sends it back: a twin that lags under load samples its ramp (A per 0.5 s)
            # below the top, by up to A * lag / 0.5 s; 0.6 A allows 0.2 s of lag.
            peaks = positions.argmax(axis=0)
            assert peaks[0] < peaks[1] < peaks[2], f"units peaked at messages {peaks} (a wave goes 1, 2, 3)"
            twin = ArrayTwin()
            for unit, i in enumerate(peaks):
                msg = states[i]
                assert msg.position[unit] >= 0.6 * A, f"unit {unit + 1} peaked at {msg.position[unit]} m"
                # the force the twin reports is the membrane's at the positions it reports
                ref = twin.solve(list(msg.position), 0.0, ("driven",) * 3)
                np.testing.assert_allclose(msg.effort, ref.force, rtol=1e-5, atol=1e-8)
                assert msg.effort[unit] > 0.0, f"unit {unit + 1} deflected without restoring force: {msg}"
                others = [msg.position[j] for j in range(3) if j != unit]
                assert max(others) < 0.5 * A  # a wave, not all units up at once
            assert controller.wave.done and controller.wave.cycle == 1
            assert h.twin_node.counters["rejected_displacement"] == 0
        finally:
            h.executor.remove_node(controller)
            controller.destroy_node()

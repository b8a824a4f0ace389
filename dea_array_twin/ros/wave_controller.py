"""A cooperative example controller: a wave passed on by self-sensing.

The paper's idea of a cooperative array is that a unit does not need to be told when
its turn has come: deflecting unit k stretches the membrane between k and k+1, the
electrode of unit k+1 grows and its capacitance rises, and that rise is the trigger
for unit k+1.  :class:`Wave` is the rule, with no ROS in it::

    wave = Wave(n_units=3, settings=WaveSettings(amplitude=0.006))
    command_m = wave.update(t_s, capacitance_F)     # call at the control rate

1. ``settle_time`` at 0 m, then the capacitances are taken as the baseline C0.
2. Unit 1 ramps linearly to ``amplitude`` in ``ramp_time``.
3. While unit k is up, the relative rise of its neighbour's capacitance
   ``C[k+1] / C0[k+1] - 1`` is watched.  When it is at least ``trigger_fraction``
   *and* unit k has reached ``amplitude``, unit k+1 ramps up while unit k ramps back
   to 0 (both in ``ramp_time``).
4. After the last unit reached ``amplitude`` and stayed there for ``settle_time`` (it
   has no neighbour to wait for) a cycle is complete: the last unit ramps back to 0,
   then the next cycle starts from unit 1 as in step 2 (there is
   no neighbour after the last unit, so this step has no capacitance trigger), or
   the wave ends after ``cycles`` cycles (0: never).

Units are taken in their numbering (row by row on a grid), so unit k+1 is the
physical neighbour of unit k along a row; across the end of a row it may be too far
away to feel unit k, and the wave then waits at unit k (the node says so).

:class:`WaveController` is the ROS 2 node around it (relative topic names, so it
runs in the twin's namespace): it learns the number of units from the first
``capacitance`` message, keeps the latest one, and publishes ``command/displacement``
(std_msgs/Float64MultiArray, m, reliable) at ``rate``.  It expects every unit of the
twin to be ``driven`` (the twin's default ``unit_modes``).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Sequence

import numpy as np
from rcl_interfaces.msg import ParameterDescriptor
from rclpy.node import Node
from std_msgs.msg import Float64MultiArray

from .node import OUTPUT_QOS, unit_array
from .params import declare_number
from .spin import spin_node

__all__ = ["Wave", "WaveSettings", "WaveEvent", "WaveController", "main"]

SETTLE, RISE, RETURN, DONE = "settle", "rise", "return", "done"


@dataclass(frozen=True)
class WaveSettings:
    """Shape and trigger of the wave (SI units).

    Attributes
    ----------
    amplitude : float
        Displacement each unit is pushed to [m] (> 0).
    ramp_time : float
        Duration of every ramp, up or down [s] (> 0).
    trigger_fraction : float
        Relative capacitance rise ``C / C0 - 1`` of the next unit that passes the
        wave on (> 0; 0.002 = +0.2 %).
    cycles : int
        Cycles before the wave stops at 0 m; 0 = forever.
    settle_time : float
        Time at 0 m before the baseline capacitances are taken [s] (>= 0).
    """

    amplitude: float = 0.008
    ramp_time: float = 1.0
    trigger_fraction: float = 0.002
    cycles: int = 0
    settle_time: float = 0.5

    def __post_init__(self) -> None:
        for name in ("amplitude", "ramp_time", "trigger_fraction"):
            value = getattr(self, name)
            if not (math.isfinite(value) and value > 0):
                raise ValueError(f"{name}: must be a finite number > 0, got {value}")
        if not (math.isfinite(self.settle_time) and self.settle_time >= 0):
            raise ValueError(f"settle_time: must be >= 0 s, got {self.settle_time}")
        if int(self.cycles) != self.cycles or self.cycles < 0:
            raise ValueError(f"cycles: must be an integer >= 0 (0 = forever), got {self.cycles}")


@dataclass(frozen=True)
class WaveEvent:
    """Something the wave did at ``time`` [s]; ``unit`` is 0-based.

    ``kind`` is ``"baseline"`` (C0 taken, unit 0 starts), ``"triggered"`` (``unit``
    starts rising after its capacitance rose by ``rise``), ``"cycle"`` (cycle
    ``cycle`` complete, ``unit`` = the last one returns to 0), ``"wrap"`` (``unit`` 0
    starts the next cycle) or ``"done"``.
    """

    time: float
    kind: str
    unit: int
    cycle: int
    rise: float = math.nan
    threshold: float = math.nan

    def describe(self) -> str:
        """One log line, units 1-based as on the command line."""
        k = self.unit + 1
        if self.kind == "baseline":
            return f"baseline capacitances taken; unit {k} starts the wave"
        if self.kind == "triggered":
            return (f"unit {k} triggered by capacitance {100 * self.rise:+.2f} % "
                    f"(threshold {100 * self.threshold:+.2f} %); unit {k - 1} returns to 0 m")
        if self.kind == "cycle":
            return f"cycle {self.cycle} complete; unit {k} returns to 0 m"
        if self.kind == "wrap":
            return f"cycle {self.cycle + 1} starts again from unit {k}"
        return f"wave finished after {self.cycle} cycle(s); all units at 0 m"


class _Ramp:
    """Linear ramp of one unit's displacement from ``start`` at ``t0`` to ``target``."""

    def __init__(self, duration: float):
        self.duration = duration
        self.t0, self.start, self.target = -math.inf, 0.0, 0.0

    def value(self, t: float) -> float:
        s = min(max((t - self.t0) / self.duration, 0.0), 1.0)
        return self.start + (self.target - self.start) * s

    def reached(self, t: float) -> bool:
        return t - self.t0 >= self.duration

    def go_to(self, t: float, target: float) -> None:
        self.start, self.t0, self.target = self.value(t), t, target


class Wave:
    """The wave rule: (time, capacitances) -> displacement command, no ROS.

    Parameters
    ----------
    n_units : int
        Number of units (>= 1).
    settings : WaveSettings, optional
        Amplitude, ramp time, trigger and cycles; defaults if omitted.

    Notes
    -----
    The command is a function of time between events, so it does not depend on how
    regularly :meth:`update` is called; a trigger is noticed at the first call at
    which both of its conditions hold.
    """

    def __init__(self, n_units: int, settings: WaveSettings | None = None):
        if n_units < 1:
            raise ValueError(f"n_units: must be >= 1, got {n_units}")
        self.n_units = int(n_units)
        self.settings = settings or WaveSettings()
        self.ramps = [_Ramp(self.settings.ramp_time) for _ in range(self.n_units)]
        self.phase = SETTLE
        self.unit = 0  #: the unit the wave is at (0-based)
        self.cycle = 0  #: completed cycles
        self.baseline: np.ndarray | None = None  #: C0 per unit [F]
        self.waiting_since: float | None = None  #: when the current unit reached amplitude [s]
        self._t_start: float | None = None
        self._events: list[WaveEvent] = []

    @property
    def done(self) -> bool:
        """The requested cycles are complete and every unit is back at 0 m."""
        return self.phase == DONE

    def rise(self, unit: int, capacitance: Sequence[float]) -> float:
        """Relative capacitance rise ``C / C0 - 1`` of ``unit`` (NaN before the baseline)."""
        if self.baseline is None:
            return math.nan
        return float(capacitance[unit]) / self.baseline[unit] - 1.0

    def pop_events(self) -> list[WaveEvent]:
        """Events since the last call, oldest first."""
        events, self._events = self._events, []
        return events

    def command(self, t: float) -> np.ndarray:
        """Displacement command per unit at time ``t`` [m]."""
        return np.array([ramp.value(t) for ramp in self.ramps])

    def update(self, t: float, capacitance: Sequence[float]) -> np.ndarray:
        """Advance the wave to time ``t`` [s] given the latest capacitances [F].

        Returns the displacement command per unit [m].
        """
        cap = np.asarray(capacitance, dtype=float)
        if cap.shape != (self.n_units,):
            raise ValueError(f"capacitance must have {self.n_units} values, got shape {cap.shape}")
        s = self.settings
        if self._t_start is None:
            self._t_start = t
        if self.phase == SETTLE and t - self._t_start >= s.settle_time:
            if not np.all(np.isfinite(cap) & (cap > 0)):
                raise ValueError(f"baseline capacitances must be finite and > 0, got {cap.tolist()}")
            self.baseline = cap.copy()
            self._start_unit(t, 0, "baseline")
        elif self.phase == RISE and self.ramps[self.unit].reached(t):
            self._rise_step(t, cap)
        elif self.phase == RETURN and self.ramps[self.unit].reached(t):
            if s.cycles and self.cycle >= s.cycles:
                self.phase = DONE
                self._events.append(WaveEvent(t, "done", self.unit, self.cycle))
            else:
                self._start_unit(t, 0, "wrap")
        return self.command(t)

    def _start_unit(self, t: float, unit: int, kind: str, rise: float = math.nan) -> None:
        self.phase, self.unit, self.waiting_since = RISE, unit, None
        self.ramps[unit].go_to(t, self.settings.amplitude)
        self._events.append(WaveEvent(t, kind, unit, self.cycle, rise, self.settings.trigger_fraction))

    def _rise_step(self, t: float, cap: np.ndarray) -> None:
        k = self.unit
        if self.waiting_since is None:
            self.waiting_since = t
        if k + 1 == self.n_units:  # the last unit is up: hold it, then the cycle is complete
            if t - self.waiting_since < self.settings.settle_time:
                return
            self.cycle += 1
            self.phase, self.waiting_since = RETURN, None
            self.ramps[k].go_to(t, 0.0)
            self._events.append(WaveEvent(t, "cycle", k, self.cycle))
            return
        rise = self.rise(k + 1, cap)
        if rise >= self.settings.trigger_fraction:
            self.ramps[k].go_to(t, 0.0)
            self._start_unit(t, k + 1, "triggered", rise)


class WaveController(Node):
    """ROS 2 node running a :class:`Wave` against the twin's ``capacitance`` output.

    Parameters (read-only): ``amplitude`` [m], ``ramp_time`` [s], ``rate`` [Hz],
    ``trigger_fraction`` [-], ``cycles`` (0 = forever), ``settle_time`` [s].
    """

    def __init__(self, **kwargs):
        super().__init__("wave_controller", **kwargs)

        def param(name: str, default: float, text: str) -> float:
            return declare_number(self, name, default, text, minimum=-math.inf)

        cycles = self.declare_parameter("cycles", 0, ParameterDescriptor(
            description="cycles before stopping at 0 m; 0 = forever", read_only=True)).value
        self.settings = WaveSettings(
            amplitude=param("amplitude", 0.008, "displacement each unit is pushed to [m]"),
            ramp_time=param("ramp_time", 1.0, "duration of each ramp up or down [s]"),
            trigger_fraction=param("trigger_fraction", 0.002,
                                   "relative capacitance rise of the next unit that passes the wave on [-]"),
            cycles=cycles, settle_time=param("settle_time", 0.5,
                                             "time at 0 m before the baseline capacitances are taken [s]"))
        self.rate = param("rate", 20.0, "command rate [Hz]")
        if not self.rate > 0:
            raise ValueError(f"rate: must be > 0 Hz, got {self.rate}")
        self.wave: Wave | None = None
        self.capacitance: np.ndarray | None = None

        self.pub = self.create_publisher(Float64MultiArray, "command/displacement", OUTPUT_QOS)
        self.create_subscription(Float64MultiArray, "capacitance", self._on_capacitance, OUTPUT_QOS)
        self.timer = self.create_timer(1.0 / self.rate, self._on_tick)
        s = self.settings
        self.get_logger().info(
            f"wave controller: amplitude {s.amplitude} m, ramp {s.ramp_time} s at {self.rate} Hz, trigger "
            f"{100 * s.trigger_fraction:+.2f} % capacitance, cycles {s.cycles or 'forever'}; waiting for capacitance")

    def _now(self) -> float:
        return self.get_clock().now().nanoseconds * 1e-9

    def _on_capacitance(self, msg: Float64MultiArray) -> None:
        cap = np.array(msg.data, dtype=float)
        if self.wave is None:
            self.wave = Wave(len(cap), self.settings)
            self.get_logger().info(f"{len(cap)} units; settling {self.settings.settle_time} s at 0 m")
        elif len(cap) != self.wave.n_units:
            self.get_logger().warning(f"ignoring capacitance with {len(cap)} values, expected {self.wave.n_units}",
                                      throttle_duration_sec=5.0)
            return
        self.capacitance = cap

    def _on_tick(self) -> None:
        wave = self.wave
        if wave is None or self.capacitance is None:
            return
        t = self._now()
        command = wave.update(t, self.capacitance)
        self.pub.publish(unit_array(command))
        for event in wave.pop_events():
            self.get_logger().info(event.describe())
        if wave.waiting_since is not None and t - wave.waiting_since > max(self.settings.ramp_time, 1.0):
            k = wave.unit
            self.get_logger().info(
                f"unit {k + 1} at {wave.settings.amplitude} m, waiting for unit {k + 2}: capacitance "
                f"{100 * wave.rise(k + 1, self.capacitance):+.3f} % of {100 * wave.settings.trigger_fraction:+.2f} %",
                throttle_duration_sec=5.0)
        if wave.done:
            self.timer.cancel()


def main(args: Sequence[str] | None = None) -> None:
    """Entry point of ``wave_controller`` (``ros2 run dea_array_twin wave_controller``)."""
    spin_node(WaveController, "wave_controller", args)


if __name__ == "__main__":
    main()

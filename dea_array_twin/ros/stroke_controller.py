"""A cooperative controller that closes the loop on capacitance only: strokes held by voltage.

The array as an actuator/sensor system (paper sections 2 and 3.2): each biased unit is
commanded by voltage alone and sensed by its capacitance alone (self-sensing).  The
paper's warning is that "a capacitive sensing strategy which ignores the intrinsic
coupling effects is destined to fail": a unit's capacitance also changes when its
neighbours move.  This module holds every unit at a stroke set-point, with the position
estimated from capacitance in one of two ways:

* :class:`SensingModel` (built from the twin, :func:`build_sensing_model`): for each unit
  ``k`` the capacitance table ``C_k(w_k, V_k)`` from driven solves with the other units
  at their rest positions and voltages, the coupling at rest to the other units'
  positions, ``a_kj = dC_k/dw_j`` (central differences), and to their voltages,
  ``b_kj = dC_k/d(V_j^2)`` (their Maxwell stress pulls on unit k's membrane), the rest
  positions ``w0`` and the quasi-static stroke curve ``w_k(V_k)`` of each unit alone
  (:func:`~dea_array_twin.model.response.stroke`) for the feedforward;
* the estimate, ignoring coupling: ``w_k = h_k(C_k, V_k)`` (``h_k`` inverts the table at
  the applied voltage); compensating it:
  ``w_k = h_k(C_k - sum_j a_kj (w_j - w0_j) - sum_j b_kj V_j^2, V_k)``, solved by a few
  Gauss-Seidel sweeps (:meth:`SensingModel.estimate`);
* the law (:class:`StrokeLoop`): ``V_k^2 = V_ff,k(w_k*)^2 + I_k`` with the integral
  ``I_k += gain dt (w_k* - w_k_estimated)`` on ``V^2`` (the electrostatic pressure is
  proportional to it), ``V`` clipped to ``[0, v_max]``.

:class:`StrokeController` is the ROS 2 node around it (relative topics, so it runs in the
twin's namespace): it keeps the latest ``capacitance``, publishes ``command/voltage``
(std_msgs/Float64MultiArray, V) at ``rate`` and follows a travelling wave of strokes
(:func:`wave_targets`).  It needs the twin's config (``config_file``) to build its map.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Sequence

import numpy as np
from rcl_interfaces.msg import ParameterDescriptor
from rclpy.node import Node
from std_msgs.msg import Float64MultiArray

from ..configfile import load_config
from ..model.config import BIASED, DRIVEN, ArrayConfig
from ..model.response import rest_state, stroke
from ..model.twin import ArrayTwin
from .node import OUTPUT_QOS, unit_array
from .params import declare_number

__all__ = ["LoopRun", "SensingModel", "StrokeController", "StrokeLoop", "build_sensing_model", "run_loop",
           "wave_targets"]


@dataclass(frozen=True)
class SensingModel:
    """What the controller knows of the array, all from the twin (SI units).

    Attributes
    ----------
    rest : ndarray, shape (n,)
        Rest positions at 0 V [m].
    positions : ndarray, shape (m,)
        Position offsets from rest of the capacitance tables [m].
    voltages : ndarray, shape (p,)
        Voltages of the tables and of the stroke curves [V].
    capacitance : ndarray, shape (n, p, m)
        ``C_k`` at ``(voltages[i], rest_k + positions[j])``, the others at rest [F].
    coupling : ndarray, shape (n, n)
        ``dC_k/dw_j`` at rest [F/m] (diagonal zero).
    voltage_coupling : ndarray, shape (n, n)
        ``dC_k/d(V_j^2)`` at rest [F/V^2] (diagonal zero).
    stroke : ndarray, shape (n, p)
        Quasi-static position of each unit alone at each voltage [m].
    """

    rest: np.ndarray
    positions: np.ndarray
    voltages: np.ndarray
    capacitance: np.ndarray
    coupling: np.ndarray
    voltage_coupling: np.ndarray
    stroke: np.ndarray

    def own_position(self, unit: int, capacitance: float, voltage: float) -> float:
        """``h_k(C, V)``: the position whose table capacitance at ``voltage`` is ``capacitance`` [m].

        Linear in ``V^2`` between the table's voltages, linear in ``w`` between its positions."""
        squared = self.voltages**2  # C varies about linearly with V^2 (the Maxwell pressure) at fixed w
        row = np.array([np.interp(voltage**2, squared, self.capacitance[unit, :, j])
                        for j in range(self.positions.size)])
        order = np.argsort(row)  # C rises with the stroke; sorted for the interpolation
        return float(self.rest[unit] + np.interp(capacitance, row[order], self.positions[order]))

    def estimate(self, capacitance: Sequence[float], voltage: Sequence[float], compensate: bool,
                 sweeps: int = 4) -> np.ndarray:
        """Positions [m] from capacitances [F] at the applied voltages [V] (see the module text)."""
        c = np.asarray(capacitance, dtype=float)
        w = np.array([self.own_position(k, c[k], v) for k, v in enumerate(voltage)])
        if not compensate:
            return w
        c = c - self.voltage_coupling @ np.asarray(voltage, dtype=float) ** 2
        for _ in range(sweeps):
            for k in range(w.size):
                others = self.coupling[k] @ (w - self.rest)
                w[k] = self.own_position(k, c[k] - others, voltage[k])
        return w

    def feedforward(self, unit: int, target: float) -> float:
        """The voltage [V] that puts ``unit`` alone at ``target`` [m] quasi-statically (its stroke curve)."""
        return float(np.interp(target, self.stroke[unit], self.voltages))


def build_sensing_model(config: ArrayConfig, v_max: float, positions: Sequence[float],
                        levels: int = 6, start: float = 0.0) -> SensingModel:
    """Build the controller's map from the twin of ``config`` (its biased units; see :class:`SensingModel`).

    ``positions`` are the offsets from rest [m] of the capacitance tables, ``levels`` the
    number of voltages in ``[0, v_max]`` (equally spaced in ``V^2``, the actuation).
    """
    twin = ArrayTwin(config)
    n = twin.n_units
    modes = config.modes
    rest = rest_state(twin, start=start).position.copy()
    voltages = v_max * np.sqrt(np.linspace(0.0, 1.0, levels))
    curves = np.empty((n, levels))
    for k in range(n):
        if modes[k] == BIASED:
            curves[k] = stroke(ArrayTwin(config), voltages, unit=k, start=start).position[:, k]
        else:
            curves[k] = rest[k]
    held = tuple(DRIVEN for _ in modes)
    probe = ArrayTwin(config)
    offsets = np.union1d(np.asarray(positions, dtype=float), [0.0])  # the rest column is needed
    table = np.empty((n, levels, offsets.size))
    for k in range(n):
        for i, volt in enumerate(voltages):
            v = np.zeros(n)
            v[k] = volt
            for j, dw in enumerate(offsets):
                d = rest.copy()
                d[k] += dw
                table[k, i, j] = probe.solve(d, v, held, check_stability=False).capacitance[k]
    coupling, voltage_coupling = np.zeros((n, n)), np.zeros((n, n))
    zero = int(np.flatnonzero(offsets == 0.0)[0])
    h = 1e-4
    for j in range(n):
        up, down = rest.copy(), rest.copy()
        up[j] += h
        down[j] -= h
        c_up = probe.solve(up, 0.0, held, check_stability=False).capacitance
        c_down = probe.solve(down, 0.0, held, check_stability=False).capacitance
        coupling[:, j] = (c_up - c_down) / (2 * h)
        v = np.zeros(n)
        v[j] = v_max
        voltage_coupling[:, j] = (probe.solve(rest, v, held, check_stability=False).capacitance - table[:, 0, zero]) \
            / v_max**2
    np.fill_diagonal(coupling, 0.0)
    np.fill_diagonal(voltage_coupling, 0.0)
    return SensingModel(rest, offsets, voltages, table, coupling, voltage_coupling, curves)


class StrokeLoop:
    """Integral control of the strokes by voltage on estimated positions (no ROS).

    Parameters
    ----------
    model : SensingModel
    compensate : bool
        Estimate positions with the coupling (True) or each unit on its own (False).
    gain : float
        Integral gain on ``V^2`` [V^2 / (m s)].
    v_max : float
        Largest voltage commanded [V].
    """

    def __init__(self, model: SensingModel, compensate: bool, gain: float, v_max: float):
        self.model, self.compensate, self.gain, self.v_max = model, compensate, gain, v_max
        self.integral = np.zeros(model.rest.size)
        self.voltage = np.zeros(model.rest.size)
        self.estimate = model.rest.copy()

    def update(self, dt: float, target: Sequence[float], capacitance: Sequence[float]) -> np.ndarray:
        """New voltages [V] for the targets [m] (absolute positions), from the capacitances just measured.

        The capacitances were measured under the voltages of the last update."""
        target = np.asarray(target, dtype=float)
        self.estimate = self.model.estimate(capacitance, self.voltage, self.compensate)
        self.integral += self.gain * dt * (target - self.estimate)
        ff = np.array([self.model.feedforward(k, t) for k, t in enumerate(target)])
        squared = np.clip(ff**2 + self.integral, 0.0, self.v_max**2)
        self.integral = squared - ff**2  # no wind-up beyond the voltage limits
        self.voltage = np.sqrt(squared)
        return self.voltage.copy()


@dataclass(frozen=True)
class LoopRun:
    """A closed-loop run on the quasi-static twin (SI units), one row per control period.

    Attributes
    ----------
    time : ndarray, shape (k,)
    target, position, voltage : ndarray, shape (k, n)
        Set-points and true positions [m] after each period, the voltages applied [V].
    sensed, estimate : ndarray, shape (k, n)
        The true positions of the state whose capacitances the controller saw at the start
        of each period, and its estimates of them [m].
    """

    time: np.ndarray
    target: np.ndarray
    position: np.ndarray
    voltage: np.ndarray
    sensed: np.ndarray
    estimate: np.ndarray

    @property
    def error(self) -> np.ndarray:
        """True position minus set-point [m]."""
        return self.position - self.target


def run_loop(twin: ArrayTwin, loop: StrokeLoop, targets, duration: float, dt: float) -> LoopRun:
    """Close ``loop`` around the quasi-static ``twin`` (at its rest state) for ``duration`` s, period ``dt``.

    Each period: the controller sees the capacitances of the last state, sets the
    voltages for ``targets(t)`` (absolute positions [m]), the twin solves there.
    """
    res = twin.last if twin.last is not None else twin.solve()
    keys = ("target", "position", "voltage", "sensed", "estimate")
    rows: dict[str, list] = {k: [] for k in ("t", *keys)}
    for i in range(int(round(duration / dt))):
        target, sensed = targets(i * dt), res.position
        voltage = loop.update(dt, target, res.capacitance)
        res = twin.solve(voltage=voltage, check_stability=False)
        for key, value in zip(("t", *keys), ((i + 1) * dt, target, res.position, voltage, sensed, loop.estimate)):
            rows[key].append(np.array(value, dtype=float))
    return LoopRun(np.array(rows["t"]), *(np.array(rows[k]) for k in keys))


def wave_targets(t: float, rest: np.ndarray, amplitude: float, period: float, offset: float = 0.0) -> np.ndarray:
    """A travelling wave of strokes: unit k at ``rest_k + offset + amplitude (1 - cos(2 pi (t/period - k/n))) / 2`` [m].

    An ``offset`` keeps every set-point above where the neighbours alone lift a unit: a
    voltage only pushes, so a unit cannot be held below that."""
    n = rest.size
    phase = 2.0 * np.pi * (t / period - np.arange(n) / n)
    return rest + offset + 0.5 * amplitude * (1.0 - np.cos(phase))


class StrokeController(Node):
    """ROS 2 node: a stroke wave held by voltage, sensed by capacitance only.

    Parameters (ROS): ``config_file`` (the twin's config YAML; required), ``rate`` [Hz],
    ``amplitude``, ``offset`` [m] and ``period`` [s] of the wave (:func:`wave_targets`),
    ``gain`` [V^2/(m s)], ``v_max`` [V], ``compensate_coupling`` (bool), ``start`` [m]
    (release height of the rest state).
    """

    def __init__(self, **kwargs):
        super().__init__("stroke_controller", **kwargs)
        path = self.declare_parameter("config_file", "", ParameterDescriptor(
            description="the twin's config YAML (biased units)", read_only=True)).value
        self.rate = declare_number(self, "rate", 20.0, "control rate [Hz]", minimum=1e-3)
        amplitude = declare_number(self, "amplitude", 0.0016, "stroke amplitude of the wave [m]")
        self.offset = declare_number(self, "offset", 0.0008, "stroke the wave starts from [m]")
        self.period = declare_number(self, "period", 8.0, "period of the wave [s]", minimum=1e-3)
        gain = declare_number(self, "gain", 2e9, "integral gain on V^2 [V^2/(m s)]")
        v_max = declare_number(self, "v_max", 2730.0, "largest voltage commanded [V]", minimum=1.0)
        start = self.declare_parameter("start", 0.0, ParameterDescriptor(
            description="release height of the biased units' rest state [m]", read_only=True)).value
        compensate = self.declare_parameter("compensate_coupling", True, ParameterDescriptor(
            description="estimate positions with the coupling between units", read_only=True)).value
        config = load_config(path or None)
        offsets = np.linspace(-0.5, 1.5, 17) * (amplitude + self.offset)
        self.model = build_sensing_model(config, v_max, offsets, levels=11, start=float(start))
        self.loop = StrokeLoop(self.model, bool(compensate), gain, v_max)
        self.amplitude = amplitude
        self.capacitance: np.ndarray | None = None
        self.targets: list[np.ndarray] = []
        self.started: float | None = None
        self.pub = self.create_publisher(Float64MultiArray, "command/voltage", OUTPUT_QOS)
        self.create_subscription(Float64MultiArray, "capacitance", self._on_capacitance, OUTPUT_QOS)
        self.create_timer(1.0 / self.rate, self._on_tick)

    def _on_capacitance(self, msg: Float64MultiArray) -> None:
        self.capacitance = np.asarray(msg.data, dtype=float)

    def _on_tick(self) -> None:
        if self.capacitance is None or self.capacitance.size != self.model.rest.size:
            return
        now = self.get_clock().now().nanoseconds * 1e-9
        self.started = now if self.started is None else self.started
        target = wave_targets(now - self.started, self.model.rest, self.amplitude, self.period, self.offset)
        self.targets.append(target)
        self.pub.publish(unit_array(self.loop.update(1.0 / self.rate, target, self.capacitance)))

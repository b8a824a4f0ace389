"""Measured runs of an array and the twin's answers to the same commands (no I/O).

A :class:`MeasuredCurve` is what calibration fits to: the held per-unit commands of
each sample, the array they were applied to, and what was measured on one unit.
:func:`simulate` runs the twin through the same commands from the flat state.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..model.config import ArrayConfig
from ..model.membrane import MODES
from ..model.twin import ArrayTwin


@dataclass(frozen=True)
class MeasuredCurve:
    """One measured curve: commands per sample and the measured unit's signals (SI).

    Attributes
    ----------
    name : str
        Where it came from, for reports (e.g. ``"run1.csv unit 2"``).
    config : ArrayConfig
        The array the commands were applied to (geometry, pre-stretch; its Yeoh
        coefficients are the starting point of a fit).
    modes : tuple of str
        ``"driven"`` or ``"free"`` per unit.
    displacement, voltage : ndarray, shape (k, n)
        Held indenter displacements [m] and voltages [V] of each sample, in the
        order they were applied.
    unit : int
        The measured unit, 0-based.
    force : ndarray, shape (k,), or None
        Measured force on that unit's indenter [N] (eq. 10 sign: positive when the
        membrane pulls the indenter back).
    capacitance : ndarray, shape (k,), or None
        Measured capacitance of that unit [F].  Fits use its change from the first
        sample, so a constant offset (leads, parasitic capacitance) does not matter.
    """

    name: str
    config: ArrayConfig
    modes: tuple[str, ...]
    displacement: np.ndarray
    voltage: np.ndarray
    unit: int
    force: np.ndarray | None = None
    capacitance: np.ndarray | None = None

    def __post_init__(self) -> None:
        n = self.config.n_units
        k = np.shape(self.displacement)[0] if np.ndim(self.displacement) == 2 else -1
        if np.shape(self.displacement) != (k, n) or np.shape(self.voltage) != (k, n) or k < 1:
            raise ValueError(f"{self.name}: displacement and voltage must have shape (samples, {n}), got "
                             f"{np.shape(self.displacement)} and {np.shape(self.voltage)}")
        if len(self.modes) != n or any(m not in MODES for m in self.modes):
            raise ValueError(f"{self.name}: modes must be {n} values out of {MODES}, got {list(self.modes)}")
        if not 0 <= self.unit < n:
            raise ValueError(f"{self.name}: measured unit {self.unit + 1} is not in 1..{n}")
        for label in ("force", "capacitance"):
            values = getattr(self, label)
            if values is not None and np.shape(values) != (k,):
                raise ValueError(f"{self.name}: {label} must have one value per sample ({k}), got {np.shape(values)}")
        if self.force is None and self.capacitance is None:
            raise ValueError(f"{self.name}: neither force nor capacitance was measured")

    @property
    def n_samples(self) -> int:
        """Number of samples."""
        return int(np.shape(self.displacement)[0])


def simulate(twin: ArrayTwin, curve: MeasuredCurve) -> tuple[np.ndarray, np.ndarray]:
    """The twin's force and capacitance for every sample of ``curve``.

    The twin is reset to the flat state, then moved through the samples in order
    (each a warm update from the previous one), as the array was.

    Parameters
    ----------
    twin : ArrayTwin
        A twin of ``curve~dea_array_twin.model.config`` (or of a config differing only in material).
    curve : MeasuredCurve
        The commands.

    Returns
    -------
    force, capacitance : ndarray, shape (k, n)
        Per sample and unit [N], [F].

    Raises
    ------
    ConvergenceError
        If a sample has no equilibrium.
    """
    twin.reset()
    force = np.empty((curve.n_samples, twin.n_units))
    capacitance = np.empty_like(force)
    for i in range(curve.n_samples):
        res = twin.solve(curve.displacement[i], curve.voltage[i], curve.modes, check_stability=False)
        force[i], capacitance[i] = res.force, res.capacitance
    return force, capacitance

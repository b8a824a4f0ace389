"""Families of bias elements a design chooses from: parameters in, bias law out.

Each family maps a parameter vector ``theta`` to a bias law ``B(w)`` [N] of
:mod:`dea_array_twin.model.bias` (pushing the indenter towards +z) and evaluates
``B`` and ``dB/dw`` for many parameter vectors at once (the inner model's optimiser
evaluates whole populations).  Parameters are chosen so that their ranges are plain
boxes:

* ``lbs``: a linear spring of positive rate, ``B = b - k (w - w_ref)``, ``k > 0`` [N/m];
  ``b`` [N] is its force at the reference height ``w_ref`` (the middle of the position
  range), so ``x0 = w_ref + b / k`` (the YAML's ``free_position``);
* ``nbs``: the same with ``k < 0``, a negative-rate bias (the paper's NBS of figures 5-6);
* ``table-family``: a measured characteristic ``T`` (a bias table: a dome, a buckled
  beam) scaled in force and shifted in position, ``B = s T(w - c)``; outside the
  shifted table ``B`` is undefined and a design that needs it is infeasible;
* ``lbs+nbs``: an LBS in parallel with a table-shaped NBS, ``B = b - k (w - w_ref) +
  s T(w - c)``.  Two *linear* springs in parallel are one linear spring (the union of
  ``lbs`` and ``nbs``), so the NBS of this family is the nonlinear element a real NBS
  is, given as a table.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass
from typing import Sequence

import numpy as np
from scipy.interpolate import PchipInterpolator

from ..model.bias import BiasLaw, LinearBias, SumBias, TableBias

FAMILIES = ("lbs", "nbs", "lbs+nbs", "table-family")


@dataclass(frozen=True)
class LinearFamily:
    """``B = b - k (w - w_ref)``: parameters ``(k [N/m], b [N])``."""

    reference: float
    stiffness: tuple[float, float]
    force: tuple[float, float]

    @property
    def names(self) -> tuple[str, ...]:
        """Parameter names with their units."""
        return ("stiffness_N_per_m", "force_at_reference_N")

    @property
    def bounds(self) -> list[tuple[float, float]]:
        """The box of the parameters."""
        return [self.stiffness, self.force]

    def evaluate(self, theta: np.ndarray, w: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """``(B, dB/dw)`` for parameters ``theta`` (..., 2) at heights ``w`` (...)."""
        k, b = theta[..., 0], theta[..., 1]
        return b - k * (w - self.reference), -k * np.ones_like(w)

    def law(self, theta: Sequence[float]) -> LinearBias:
        """The bias law of one parameter vector."""
        k, b = float(theta[0]), float(theta[1])
        return LinearBias(k, self.reference + b / k)


@dataclass(frozen=True)
class TableFamily:
    """``B = s T(w - c)``: parameters ``(s [-], c [m])`` of a characteristic ``T`` given as a table."""

    table: TableBias
    scale: tuple[float, float]
    shift: tuple[float, float]

    @property
    def names(self) -> tuple[str, ...]:
        """Parameter names with their units."""
        return ("force_scale", "position_shift_m")

    @property
    def bounds(self) -> list[tuple[float, float]]:
        """The box of the parameters."""
        return [self.scale, self.shift]

    @functools.cached_property
    def _curves(self) -> tuple[PchipInterpolator, PchipInterpolator]:
        curve = PchipInterpolator(np.asarray(self.table.position), np.asarray(self.table.force_N), extrapolate=False)
        return curve, curve.derivative()

    def evaluate(self, theta: np.ndarray, w: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """``(B, dB/dw)``; NaN outside the shifted table (no extrapolation)."""
        curve, slope = self._curves
        s, c = theta[..., 0], theta[..., 1]
        return s * curve(w - c), s * slope(w - c)

    def law(self, theta: Sequence[float]) -> TableBias:
        """The bias law of one parameter vector: the table scaled and shifted."""
        s, c = float(theta[0]), float(theta[1])
        return TableBias(tuple(p + c for p in self.table.position), tuple(s * f for f in self.table.force_N))


@dataclass(frozen=True)
class SumFamily:
    """Laws in parallel: the parameters of each part one after the other."""

    parts: tuple

    @property
    def names(self) -> tuple[str, ...]:
        """Parameter names with their units."""
        return tuple(name for part in self.parts for name in part.names)

    @property
    def bounds(self) -> list[tuple[float, float]]:
        """The box of the parameters."""
        return [b for part in self.parts for b in part.bounds]

    def _split(self, theta):
        start = 0
        for part in self.parts:
            size = len(part.names)
            yield part, theta[..., start:start + size]
            start += size

    def evaluate(self, theta: np.ndarray, w: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """``(B, dB/dw)``: the sums over the parts."""
        force, slope = np.zeros_like(w), np.zeros_like(w)
        for part, sub in self._split(theta):
            b, db = part.evaluate(sub, w)
            force, slope = force + b, slope + db
        return force, slope

    def law(self, theta: Sequence[float]) -> SumBias:
        """The bias law of one parameter vector: a ``sum`` of the parts' laws."""
        theta = np.asarray(theta, dtype=float)
        return SumBias(tuple(part.law(sub) for part, sub in self._split(theta)))


Family = LinearFamily | TableFamily | SumFamily


@dataclass(frozen=True)
class Ranges:
    """The boxes of a family's parameters; None picks the default from the membrane's scales.

    Attributes
    ----------
    stiffness : (float, float) or None
        Rate ``k`` of a linear spring [N/m].  Defaults: ``lbs`` 0.1-10, ``nbs`` -2 to -0.01
        times the membrane's stiffness scale (see :func:`make_family`).
    force : (float, float) or None
        A linear spring's force at the reference height [N]; default 0 to twice the
        membrane's largest 0 V force over the position range.
    scale : (float, float) or None
        Force factor of a table [-]; default 0.25-4.
    shift : (float, float) or None
        Position shift of a table [m]; default: the table's middle anywhere in the position
        range.
    """

    stiffness: tuple[float, float] | None = None
    force: tuple[float, float] | None = None
    scale: tuple[float, float] | None = None
    shift: tuple[float, float] | None = None


def make_family(name: str, position_range: tuple[float, float], stiffness_scale: float, force_scale: float,
                ranges: Ranges = Ranges(), table: TableBias | None = None) -> Family:
    """The family ``name`` with its parameter boxes.

    Parameters
    ----------
    name : str
        One of :data:`FAMILIES`.
    position_range : (float, float)
        Where the units may be [m]; its middle is the linear springs' reference height.
    stiffness_scale : float
        The membrane's stiffness [N/m] the default rate ranges are relative to (the
        smallest 0 V slope of the designed units' nominal curves at the reference height).
    force_scale : float
        The membrane's largest 0 V force over the position range [N].
    ranges : Ranges
        Boxes given by the user (None: the defaults).
    table : TableBias, optional
        The characteristic of ``table-family`` and of the NBS of ``lbs+nbs``.

    Raises
    ------
    ValueError
        Unknown family, a range of the wrong sign or empty, a table family without a table.
    """
    if name not in FAMILIES:
        raise ValueError(f"unknown bias family {name!r}; known: {list(FAMILIES)}")
    lo, hi = position_range
    reference = 0.5 * (lo + hi)

    def box(label: str, given, default) -> tuple[float, float]:
        out = tuple(float(v) for v in (given if given is not None else default))
        if not (len(out) == 2 and np.all(np.isfinite(out)) and out[0] < out[1]):
            raise ValueError(f"{label} range must be two finite numbers LO < HI, got {list(out)}")
        return out

    def linear(sign: float) -> LinearFamily:
        default = (0.1 * stiffness_scale, 10.0 * stiffness_scale) if sign > 0 else \
            (-2.0 * stiffness_scale, -0.01 * stiffness_scale)
        k = box("stiffness", ranges.stiffness, default)
        if (sign > 0 and k[0] <= 0) or (sign < 0 and k[1] >= 0):
            kind = "an LBS needs rates > 0" if sign > 0 else "an NBS needs rates < 0"
            raise ValueError(f"stiffness range {list(k)} N/m: {kind}")
        return LinearFamily(reference, k, box("force", ranges.force, (0.0, 2.0 * force_scale)))

    def tabled() -> TableFamily:
        if table is None:
            raise ValueError(f"--bias {name} needs the NBS characteristic as a table (--table FILE, or a table "
                             "bias in the config)")
        middle = 0.5 * (table.position[0] + table.position[-1])
        return TableFamily(table, box("scale", ranges.scale, (0.25, 4.0)),
                           box("shift", ranges.shift, (lo - middle, hi - middle)))

    if name == "lbs":
        return linear(1.0)
    if name == "nbs":
        return linear(-1.0)
    if name == "table-family":
        return tabled()
    return SumFamily((linear(1.0), tabled()))


def find_table(law: BiasLaw) -> TableBias | None:
    """The table in a config's bias law (itself, or the first among a sum's terms), if any."""
    if isinstance(law, TableBias):
        return law
    if isinstance(law, SumBias):
        return next((t for t in law.terms if isinstance(t, TableBias)), None)
    return None

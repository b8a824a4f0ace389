"""Bias elements of actuator units: the force ``B(w)`` that pushes an indenter towards +z.

A biased unit's rigid indenter at height ``w`` [m] is pushed towards +z (the direction
of positive displacement) by its bias element with ``B(w)`` [N] (paper section 2: a
linear spring LBS, a negative-rate spring NBS such as a buckled beam or a bistable
dome, magnets, a dead weight).  Every law gives the force, its derivative ``dB/dw``
[N/m] (the bias stiffness is ``-dB/dw``: it enters the tangent and the stability
check) and the work ``W(w) = int_{w_ref}^{w} B dw'`` [J] (the bias's potential energy
is ``-W``; ``w_ref`` is 0 except for a table, where it is the first position).

Laws (YAML entries of the ``bias`` config field, a list with one entry per unit or
one for all; ``null`` is ``none``):

* ``{type: none}``: ``B = 0`` (force control: only the commanded force acts);
* ``{type: linear, stiffness: k, free_position: x0}``: ``B = k (x0 - w)``; ``k < 0``
  is a negative-rate bias (NBS);
* ``{type: constant, force: f0}``: ``B = f0`` (a dead weight ``m g`` pushing up is
  ``f0 = m g``, one resting on top ``f0 = -m g``);
* ``{type: table, position: [w_i], force: [B_i]}``: measured pairs, monotone cubic
  (PCHIP) interpolation; a position outside ``[w_0, w_n]`` is an error
  (:class:`BiasRangeError`), never an extrapolation;
* ``{type: sum, terms: [<entries>]}``: the sum of several laws (an LBS and an NBS in
  parallel).

Positions and forces are what the twin uses (m, N); unlike the membrane's lengths
they are not multiplied by the config's ``scale``: a bias element is a part of its
own, not part of the membrane geometry.
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass
from typing import Any, Mapping, Union

import numpy as np
from scipy.interpolate import PchipInterpolator

__all__ = ["BiasLaw", "BiasRangeError", "ConstantBias", "LinearBias", "NoBias", "SumBias", "TableBias",
           "bias_from_entry"]


class BiasRangeError(ValueError):
    """A bias table was asked for a position outside its range."""


class _Law:
    """What every law answers besides force, slope and work."""

    #: ``B`` is affine in ``w`` (its slope is constant): one evaluation gives it everywhere.
    affine = True

    def contains(self, w: float) -> bool:
        """Whether the law is defined at ``w`` (only a table has a range)."""
        return True


@dataclass(frozen=True)
class NoBias(_Law):
    """``B = 0``: force control, only the commanded external force acts."""

    kind = "none"

    def force(self, w: float) -> float:
        """``B(w)`` [N]."""
        return 0.0

    def slope(self, w: float) -> float:
        """``dB/dw`` [N/m]."""
        return 0.0

    def work(self, w: float) -> float:
        """``int_0^w B dw`` [J]."""
        return 0.0

    def to_dict(self) -> dict[str, Any]:
        """The YAML entry of this law."""
        return {"type": self.kind}


@dataclass(frozen=True)
class LinearBias(_Law):
    """``B = k (x0 - w)``: a spring of stiffness ``k`` [N/m], free at ``x0`` [m]; ``k < 0``: an NBS."""

    stiffness: float
    free_position: float
    kind = "linear"

    def force(self, w: float) -> float:
        """``B(w) = k (x0 - w)`` [N]."""
        return self.stiffness * (self.free_position - w)

    def slope(self, w: float) -> float:
        """``dB/dw = -k`` [N/m]."""
        return -self.stiffness

    def work(self, w: float) -> float:
        """``int_0^w B dw = k (x0 w - w^2 / 2)`` [J]."""
        return self.stiffness * (self.free_position * w - 0.5 * w * w)

    def to_dict(self) -> dict[str, Any]:
        """The YAML entry of this law."""
        return {"type": self.kind, "stiffness": self.stiffness, "free_position": self.free_position}


@dataclass(frozen=True)
class ConstantBias(_Law):
    """``B = f0`` [N]: a dead weight (or a constant-force spring)."""

    force_N: float
    kind = "constant"

    def force(self, w: float) -> float:
        """``B(w) = f0`` [N]."""
        return self.force_N

    def slope(self, w: float) -> float:
        """``dB/dw = 0``."""
        return 0.0

    def work(self, w: float) -> float:
        """``int_0^w B dw = f0 w`` [J]."""
        return self.force_N * w

    def to_dict(self) -> dict[str, Any]:
        """The YAML entry of this law."""
        return {"type": self.kind, "force": self.force_N}


@dataclass(frozen=True)
class TableBias(_Law):
    """Measured ``(w_i, B_i)`` pairs, monotone cubic (PCHIP) in between, an error outside.

    PCHIP (Fritsch-Carlson) keeps the interpolant monotone wherever the data are, so a
    measured characteristic gets no spurious wiggles (and no spurious equilibria).
    """

    position: tuple[float, ...]
    force_N: tuple[float, ...]
    kind = "table"
    affine = False

    @functools.cached_property
    def _curve(self) -> PchipInterpolator:
        return PchipInterpolator(np.asarray(self.position), np.asarray(self.force_N), extrapolate=False)

    @functools.cached_property
    def _antiderivative(self):
        return self._curve.antiderivative()

    @functools.cached_property
    def _derivative(self):
        return self._curve.derivative()

    def _check(self, w: float) -> None:
        lo, hi = self.position[0], self.position[-1]
        if not lo <= w <= hi:
            raise BiasRangeError(f"position {w:.6g} m is outside the bias table [{lo:.6g}, {hi:.6g}] m "
                                 f"(a table is not extrapolated)")

    def contains(self, w: float) -> bool:
        """Whether ``w`` lies inside the table."""
        return self.position[0] <= w <= self.position[-1]

    def force(self, w: float) -> float:
        """``B(w)`` [N], PCHIP; :class:`BiasRangeError` outside the table."""
        self._check(w)
        return float(self._curve(w))

    def slope(self, w: float) -> float:
        """``dB/dw`` [N/m] of the PCHIP interpolant."""
        self._check(w)
        return float(self._derivative(w))

    def work(self, w: float) -> float:
        """``int_{w_0}^w B dw`` [J] from the first table position."""
        self._check(w)
        return float(self._antiderivative(w))

    def to_dict(self) -> dict[str, Any]:
        """The YAML entry of this law."""
        return {"type": self.kind, "position": list(self.position), "force": list(self.force_N)}


@dataclass(frozen=True)
class SumBias(_Law):
    """The sum of several laws acting in parallel."""

    terms: tuple["BiasLaw", ...]
    kind = "sum"

    @property
    def affine(self) -> bool:  # noqa: D102 (documented in _Law)
        return all(t.affine for t in self.terms)

    def force(self, w: float) -> float:
        """``sum B_i(w)`` [N]."""
        return math.fsum(t.force(w) for t in self.terms)

    def slope(self, w: float) -> float:
        """``sum dB_i/dw`` [N/m]."""
        return math.fsum(t.slope(w) for t in self.terms)

    def work(self, w: float) -> float:
        """``sum W_i(w)`` [J]."""
        return math.fsum(t.work(w) for t in self.terms)

    def contains(self, w: float) -> bool:
        """Whether every table among the terms covers ``w``."""
        return all(t.contains(w) for t in self.terms)

    def to_dict(self) -> dict[str, Any]:
        """The YAML entry of this law."""
        return {"type": self.kind, "terms": [t.to_dict() for t in self.terms]}


BiasLaw = Union[NoBias, LinearBias, ConstantBias, TableBias, SumBias]

#: Fields of each law's YAML entry (besides ``type``).
FIELDS = {"none": (), "linear": ("stiffness", "free_position"), "constant": ("force",),
          "table": ("position", "force"), "sum": ("terms",)}


def _number(entry: Mapping, key: str) -> float:
    value = entry[key]
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
        raise ValueError(f"{key}: expected a finite number, got {value!r}")
    return float(value)


def _numbers(entry: Mapping, key: str) -> tuple[float, ...]:
    value = entry[key]
    if isinstance(value, (str, bytes, Mapping)) or not hasattr(value, "__iter__"):
        raise ValueError(f"{key}: expected a list of numbers, got {value!r}")
    out = []
    for i, v in enumerate(value):
        if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v):
            raise ValueError(f"{key}[{i}]: expected a finite number, got {v!r}")
        out.append(float(v))
    return tuple(out)


def bias_from_entry(entry: Any) -> BiasLaw:
    """A bias law from its YAML entry (a mapping with ``type``), ``None`` (no bias) or a law.

    Raises
    ------
    ValueError
        Unknown type, unknown or missing field, a bad value; the message names it
        (the config prefixes the entry, e.g. ``bias[1]: ...``).
    """
    if entry is None:
        return NoBias()
    if isinstance(entry, (NoBias, LinearBias, ConstantBias, TableBias, SumBias)):
        return entry
    if not isinstance(entry, Mapping):
        raise ValueError(f"expected a mapping with 'type' (or null), got {entry!r}")
    kind = entry.get("type")
    if kind not in FIELDS:
        raise ValueError(f"unknown bias type {kind!r}; known types: {list(FIELDS)}")
    fields = FIELDS[kind]
    unknown = sorted(set(entry) - set(fields) - {"type"})
    if unknown:
        raise ValueError(f"unknown field(s) {unknown} for a {kind} bias; its fields: {list(fields)}")
    missing = [f for f in fields if f not in entry]
    if missing:
        raise ValueError(f"a {kind} bias needs {list(fields)}; missing {missing}")
    if kind == "none":
        return NoBias()
    if kind == "linear":
        return LinearBias(_number(entry, "stiffness"), _number(entry, "free_position"))
    if kind == "constant":
        return ConstantBias(_number(entry, "force"))
    if kind == "table":
        position, force = _numbers(entry, "position"), _numbers(entry, "force")
        if len(position) < 2 or len(position) != len(force):
            raise ValueError(f"a table needs >= 2 positions and one force per position, got {len(position)} "
                             f"positions and {len(force)} forces")
        if any(b <= a for a, b in zip(position, position[1:])):
            raise ValueError(f"position: must be strictly increasing, got {list(position)}")
        return TableBias(position, force)
    terms = entry["terms"]
    if isinstance(terms, (str, bytes, Mapping)) or not hasattr(terms, "__iter__") or not len(terms):
        raise ValueError(f"terms: expected a non-empty list of bias entries, got {terms!r}")
    laws = []
    for i, term in enumerate(terms):
        try:
            laws.append(bias_from_entry(term))
        except ValueError as exc:
            raise ValueError(f"terms[{i}]: {exc}") from None
    return SumBias(tuple(laws))

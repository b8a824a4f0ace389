"""A reduced-order model (ROM) of one array as plain arrays: its envelope, basis and sampled points.

:class:`ReducedModel` is what training (:mod:`.rom_build`) produces and what
:class:`~.reduced_twin.ReducedTwin` runs; :meth:`ReducedModel.to_arrays` /
:meth:`ReducedModel.from_arrays` turn it into a flat dict of arrays and back, which
a layer above writes to and reads from a ``.npz`` file (this module does no I/O).
A ROM belongs to one configuration: :func:`config_hash` of the config it was trained
on is stored with it, and :func:`check_config` refuses it for any other.

The reduced state (paper eqs. 8-9 hold exactly: the frame and the indenter disks are
in ``x_ref`` and the liftings, and ``V`` is zero on every prescribed dof):

    x = x_ref + sum_k d_k L_k + V q

with ``x_ref`` the flat pre-stretched membrane, ``L_k`` the lifting of driven unit k
(the linear response of the pre-stretched membrane at 0 V to a unit displacement of
its indenter: ``L_k = e_k - K_ff^-1 K_fp e_k``), and ``V`` (n_dofs x r) an orthonormal
POD basis of the snapshots minus their liftings.
"""

from __future__ import annotations

import hashlib
import json
from dataclasses import dataclass, field
from typing import Sequence

import numpy as np
from scipy.stats import qmc

from .config import ArrayConfig
from .membrane import DRIVEN, FREE, check_modes

#: Format version of :meth:`ReducedModel.to_arrays`; a file of another version is refused.
FORMAT_VERSION = 1


class RomMismatchError(ValueError):
    """A ROM does not belong to the configuration (or the file format) it is used with."""


#: Config fields that bound, label or choose commands, or describe what lies outside the membrane,
#: without changing the membrane's equations (the node may change the first three at run time): a
#: ROM does not depend on them.  The unit modes it answers are those of its envelope, and biased
#: units where it has driven ones (the bias elements, masses, damping and contact of biased units
#: act on the indenter heights, which the reduced twin solves for); others go to the FE.
UNCHECKED_FIELDS = ("max_displacement", "breakdown_field", "unit_modes", "experimental_hv_prestretch",
                    "experimental_hv_voltage", "bias", "mass", "damping", "contact")


def _model_fields(cfg: ArrayConfig) -> dict:
    return {k: v for k, v in cfg.to_dict().items() if k not in UNCHECKED_FIELDS}


def config_hash(cfg: ArrayConfig) -> str:
    """A short hash of every config field that enters the model (all but :data:`UNCHECKED_FIELDS`):
    a ROM is valid for exactly one such configuration."""
    text = json.dumps(_model_fields(cfg), sort_keys=True)
    return hashlib.sha256(text.encode()).hexdigest()[:16]


@dataclass(frozen=True)
class Envelope:
    """The commands a ROM was trained on: one box per unit, for one set of unit modes.

    Attributes
    ----------
    modes : tuple of str
        Unit modes (``"driven"``/``"free"``) the ROM was trained for.
    displacement_min, displacement_max : ndarray, shape (n_units,)
        Indenter displacement range per unit [m] (NaN for free units).
    voltage_min, voltage_max : ndarray, shape (n_units,)
        Voltage range per unit [V].
    """

    modes: tuple
    displacement_min: np.ndarray
    displacement_max: np.ndarray
    voltage_min: np.ndarray
    voltage_max: np.ndarray

    @classmethod
    def box(cls, modes: Sequence[str], displacement: tuple[float, float], voltage: tuple[float, float]) -> "Envelope":
        """The same displacement range [m] for every driven unit and voltage range [V] for every unit."""
        modes = check_modes(modes, len(modes))
        if any(m not in (DRIVEN, FREE) for m in modes):
            raise ValueError(f"a ROM envelope holds driven and free units only (train a biased unit as driven: "
                             f"the reduced twin solves for its height), got modes {list(modes)}")
        n = len(modes)
        lo, hi = float(displacement[0]), float(displacement[1])
        vlo, vhi = float(voltage[0]), float(voltage[1])
        if not lo <= hi:
            raise ValueError(f"displacement range must have min <= max, got [{lo}, {hi}] m")
        if not 0.0 <= vlo <= vhi:
            raise ValueError(f"voltage range must have 0 <= min <= max, got [{vlo}, {vhi}] V")
        driven = np.array([m == DRIVEN for m in modes])
        return cls(modes, np.where(driven, lo, np.nan), np.where(driven, hi, np.nan), np.full(n, vlo),
                   np.full(n, vhi))

    @property
    def n_units(self) -> int:
        """Number of units."""
        return len(self.modes)

    @property
    def driven(self) -> np.ndarray:
        """Indices of the driven units (those with a lifting and a displacement input)."""
        return np.array([k for k, m in enumerate(self.modes) if m == DRIVEN], dtype=np.int64)

    def violation(self, displacement: np.ndarray, voltage: np.ndarray, modes: Sequence[str],
                  margin: float = 1e-9) -> str | None:
        """Why a command lies outside the envelope, or None if it lies inside.

        ``margin`` is a relative slack on each range (rounding of commands at its edges).
        """
        if tuple(modes) != self.modes:
            return f"unit modes {list(modes)} differ from the trained {list(self.modes)}"
        k = self.driven
        d = np.asarray(displacement, float)[k]
        lo, hi = self.displacement_min[k], self.displacement_max[k]
        slack = margin * np.maximum(hi - lo, 1e-12)
        bad = np.flatnonzero((d < lo - slack) | (d > hi + slack))
        if bad.size:
            u = int(k[bad[0]])
            return (f"displacement {d[bad[0]]:.6g} m of unit {u + 1} outside the trained "
                    f"[{self.displacement_min[u]:.6g}, {self.displacement_max[u]:.6g}] m")
        v = np.asarray(voltage, float)
        slack = margin * np.maximum(self.voltage_max - self.voltage_min, 1.0)
        bad = np.flatnonzero((v < self.voltage_min - slack) | (v > self.voltage_max + slack))
        if bad.size:
            u = int(bad[0])
            return (f"voltage {v[u]:.6g} V of unit {u + 1} outside the trained "
                    f"[{self.voltage_min[u]:.6g}, {self.voltage_max[u]:.6g}] V")
        return None

    def sample(self, n: int, seed: int, edges: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
        """``n`` commands spread over the envelope (Latin hypercube): displacements (n, n_units) [m], voltages [V].

        Free units get displacement 0 (ignored by the model).  The last ``edges`` share of the
        commands (0 to 1) has its coordinates stretched towards the bounds, ``(1 - cos(pi u)) / 2``
        (the Chebyshev density, 2.9 times as many values within 5 % of a bound as a uniform sample):
        the corners of the box, a unit at a bound among neighbours at theirs, are where a uniform
        sample of many inputs is thinnest (``docs/rom.md``).
        """
        if not 0.0 <= edges <= 1.0:
            raise ValueError(f"edges must be a share in [0, 1], got {edges}")
        k = self.driven
        dims = k.size + self.n_units
        unit = qmc.LatinHypercube(d=dims, seed=seed).random(n)
        stretched = np.arange(n) >= n - round(edges * n)
        unit[stretched] = 0.5 * (1.0 - np.cos(np.pi * unit[stretched]))
        d = np.zeros((n, self.n_units))
        d[:, k] = self.displacement_min[k] + unit[:, :k.size] * (self.displacement_max[k] - self.displacement_min[k])
        v = self.voltage_min + unit[:, k.size:] * (self.voltage_max - self.voltage_min)
        return d, v

    def to_arrays(self) -> dict[str, np.ndarray]:
        """The envelope as arrays (for :meth:`ReducedModel.to_arrays`)."""
        return {"envelope_modes": np.array(self.modes), "envelope_displacement_min": self.displacement_min,
                "envelope_displacement_max": self.displacement_max, "envelope_voltage_min": self.voltage_min,
                "envelope_voltage_max": self.voltage_max}

    @classmethod
    def from_arrays(cls, arrays: dict) -> "Envelope":
        """Inverse of :meth:`to_arrays`."""
        return cls(tuple(str(m) for m in arrays["envelope_modes"]),
                   *(np.asarray(arrays[f"envelope_{n}"], float) for n in
                     ("displacement_min", "displacement_max", "voltage_min", "voltage_max")))


@dataclass(frozen=True)
class ReducedModel:
    """Everything a :class:`~.reduced_twin.ReducedTwin` needs besides the mesh (SI units).

    Attributes
    ----------
    config : dict
        The training configuration (:meth:`ArrayConfig.to_dict`); ``config_hash`` is its hash.
    config_hash : str
    envelope : Envelope
    reference : ndarray, shape (n_dofs,)
        ``x_ref``, the flat pre-stretched membrane [m].
    lift : ndarray, shape (n_dofs, nd)
        Lifting vector of each driven unit [m/m].
    basis : ndarray, shape (n_dofs, r)
        Orthonormal POD basis ``V`` [-] (coefficients ``q`` in m).
    enrichment : ndarray, shape (n_dofs, nw)
        Orthonormal vectors ``W`` outside ``V`` that the error indicator tests the
        reduced residual along (next POD modes, linear responses to each voltage and
        indenter at two states).
    point_element, point_index : ndarray of int, shape (n_points,)
        Element and quadrature point of each sampled point.
    point_weight : ndarray, shape (n_points,)
        ECSW weight times ``t0`` times the point's reference area [m^3]; 0 for the
        monitor points (read for the peak field and smallest stress, not summed).
    force_reference : ndarray, shape (n_units,)
        Largest |force| of each unit over the training snapshots [N]: the full scale
        of the force errors (tolerances and the validation table are relative to it).
    tolerance : float
        Relative error above which the indicator sends an update to the FE.
    indicator_scale : float
        What the raw indicator is multiplied by (at least 1): the largest ratio of error
        to raw indicator over the calibration commands of training
        (:func:`dea_array_twin.rom.train.indicator_scale`); 1 for a ROM trained before it.
    train_parameters : ndarray, shape (n_snapshots, nd + n_units)
        Driven displacements [m] and voltages [V] of the training snapshots.
    train_coordinates : ndarray, shape (n_snapshots, r)
        Their reduced coordinates ``q`` (cold starts begin at the nearest one).
    singular_values : ndarray
        POD singular values of the snapshots (all of them, for the record).
    validation : dict
        The validation table and training facts (JSON-able).
    """

    config: dict
    config_hash: str
    envelope: Envelope
    reference: np.ndarray
    lift: np.ndarray
    basis: np.ndarray
    enrichment: np.ndarray
    point_element: np.ndarray
    point_index: np.ndarray
    point_weight: np.ndarray
    force_reference: np.ndarray
    tolerance: float
    train_parameters: np.ndarray
    train_coordinates: np.ndarray
    singular_values: np.ndarray
    validation: dict = field(default_factory=dict)
    indicator_scale: float = 1.0

    @property
    def n_modes(self) -> int:
        """Number of POD modes r."""
        return self.basis.shape[1]

    @property
    def n_points(self) -> int:
        """Number of sampled points with a positive weight."""
        return int(np.count_nonzero(self.point_weight > 0))

    def validation_warning(self) -> str:
        """What its validation table says against using it, or '' (errors within :attr:`tolerance`, every
        held-out command answered by the reduced model).

        A ROM whose held-out errors exceeded its tolerance may answer that far off the FE; the
        text says how far, on how many commands, and how many of those the error indicator
        missed (it does not see every error on large arrays: ``docs/rom.md``).  A ROM that handed
        held-out commands to the FE (its Newton did not converge) answers such commands at the
        FE's speed; the text says on how many.
        """
        facts = self.validation
        if "force_error_max" not in facts:
            return ""
        force, capacitance = facts["force_error_max"], facts["capacitance_error_max"]
        parts = []
        if max(force, capacitance) > self.tolerance:
            parts.append(f"its validation found errors above its tolerance {self.tolerance:.3%} (force up to "
                         f"{force:.3%}, capacitance up to {capacitance:.3%}) on {facts['over_tolerance']} of "
                         f"{facts['commands']} held-out commands, {facts['over_tolerance_unflagged']} of them missed "
                         f"by the error indicator: an update it answers may be that far off the FE")
        if facts.get("rom_fallbacks"):
            parts.append(f"it handed {facts['rom_fallbacks']} of {facts['commands']} held-out commands to the FE "
                         f"(its Newton did not converge there): updates near them run at the FE's speed")
        return "; ".join(parts)

    _ARRAYS = ("reference", "lift", "basis", "enrichment", "point_element", "point_index", "point_weight",
               "force_reference", "train_parameters", "train_coordinates", "singular_values")

    def to_arrays(self) -> dict[str, np.ndarray]:
        """A flat dict of arrays (strings as 0-d arrays, the dicts as JSON) for ``numpy.savez``."""
        out = {name: getattr(self, name) for name in self._ARRAYS}
        out.update(self.envelope.to_arrays())
        out.update(format_version=np.array(FORMAT_VERSION), config=np.array(json.dumps(self.config)),
                   config_hash=np.array(self.config_hash), tolerance=np.array(self.tolerance),
                   indicator_scale=np.array(self.indicator_scale), validation=np.array(json.dumps(self.validation)))
        return out

    @classmethod
    def from_arrays(cls, arrays: dict) -> "ReducedModel":
        """Inverse of :meth:`to_arrays`; a mapping such as ``numpy.load(path)`` works.

        Raises
        ------
        RomMismatchError
            For another format version or a missing array.
        """
        version = int(arrays["format_version"]) if "format_version" in arrays else None
        if version != FORMAT_VERSION:
            raise RomMismatchError(f"ROM format version {version}, this dea_array_twin reads version "
                                   f"{FORMAT_VERSION}: train the ROM again")
        try:
            values = {name: np.asarray(arrays[name]) for name in cls._ARRAYS}
            return cls(config=json.loads(str(arrays["config"])), config_hash=str(arrays["config_hash"]),
                       envelope=Envelope.from_arrays(arrays), tolerance=float(arrays["tolerance"]),
                       indicator_scale=float(arrays["indicator_scale"]) if "indicator_scale" in arrays else 1.0,
                       validation=json.loads(str(arrays["validation"])), **values)
        except KeyError as exc:
            raise RomMismatchError(f"ROM data lacks the array {exc.args[0]!r}") from None


def check_config(rom: ReducedModel, cfg: ArrayConfig) -> None:
    """Refuse ``rom`` unless it was trained on exactly ``cfg``; the error names the fields that differ.

    The stored hash is the fast path; a ROM whose hash differs while every model field
    agrees (one stamped when :data:`UNCHECKED_FIELDS` was shorter) is accepted."""
    if rom.config_hash == config_hash(cfg):
        return
    ours = _model_fields(cfg)
    differ = sorted(k for k in (set(ours) | set(rom.config)) - set(UNCHECKED_FIELDS)
                    if ours.get(k) != rom.config.get(k))
    if not differ:
        return
    detail = ", ".join(f"{k}: ROM {rom.config.get(k)!r}, config {ours.get(k)!r}" for k in differ[:6])
    raise RomMismatchError(f"the ROM was trained for another configuration (hash {rom.config_hash}, this config "
                           f"{config_hash(cfg)}); differing fields: {detail}")

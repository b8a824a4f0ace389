"""The twin's typed configuration, with the paper's Table 1 as defaults.

All lengths are in metres *before* the in-plane ``scale`` factor is applied; the
``scaled_*`` properties return the lengths the model uses.  Thickness is never
scaled (the paper's area-scaling study keeps t0).
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from .bias import BiasLaw, NoBias, bias_from_entry
from .material import EPS0, Yeoh

LAYOUTS = ("array", "circular")
#: Table fields (tuples of float, given as any sequence of numbers).
_TABLES = ("slip_displacement", "slip_factor", "experimental_hv_prestretch", "experimental_hv_voltage")
SHAPES = ("circle", "square")
#: Unit modes: indenter position imposed, no indenter, indenter on a bias element.
DRIVEN, FREE, BIASED = "driven", "free", "biased"
MODES = (DRIVEN, FREE, BIASED)
#: Per-unit fields: one entry for every unit, or one per unit.
UNIT_FIELDS = ("unit_modes", "bias", "mass", "damping", "contact")


class ConfigError(ValueError):
    """A configuration value is out of its allowed range; the message names the field."""


@dataclass(frozen=True)
class ArrayConfig:
    """Geometry, material, mesh and solver settings of a DE array.

    Defaults are Table 1 of Croce et al. with ``lp = 1.10``.  Units: SI.

    Attributes
    ----------
    layout : str
        ``"array"``: rectangular frame ``length x width`` holding ``rows x cols``
        units on a centred grid.  ``"circular"``: one unit in a circular frame of
        radius ``frame_radius`` (the classic cone DEA).
    rows, cols : int
        Units per column and per row (``"array"`` only).  Units are numbered row by
        row from the top left, 0-based in code and 1-based on the command line.
    length, width : float
        Frame size L along x and H along y [m].
    frame_radius : float
        Frame radius [m] (``"circular"`` only).
    electrode_diameter : float
        Electrode diameter D [m].  Square electrodes have the same area
        (side ``sqrt(pi) D / 2``) and the same centres.
    spacing : float
        Gap d between neighbouring circular electrodes [m]; pitch = D + d.
    indenter_radius : float
        Radius r of the rigid indenter disk at each electrode centre [m].
    electrode_shape : str
        ``"circle"`` or ``"square"``.
    scale : float
        In-plane scale factor applied to every length above (not to thickness).
    thickness : float
        Unstretched membrane thickness t0 [m].
    epsr : float
        Relative permittivity.
    c10, c20, c30 : float
        Yeoh coefficients [Pa].
    prestretch : float
        Equi-biaxial pre-stretch lp applied by the frame (> 1).
    breakdown_field : float
        True electric field [V/m] above which a result is flagged.
    element_order : int
        1 (3-node) or 2 (6-node, curved edges) triangles.
    mesh_size : float
        Element size far from the indenters [m, before scaling].
    mesh_size_indenter : float
        Element size on the indenter edges [m, before scaling].
    mesh_size_electrode : float
        Element size on the electrode edges [m, before scaling].
    max_displacement : float
        Largest |d_k| [m, before scaling] a command may ask for.
    slip_displacement, slip_factor : tuple of float
        Optional slip correction of the frame (paper eq. 11), a table of the factor
        gamma [-] against the indenter displacement [m, before scaling; scaled like
        every length, as ``max_displacement`` is, so a table carries over to a
        scaled array at the same relative deflection].  Piecewise linear between
        the entries, constant beyond the ends; displacements strictly increasing
        and >= 0; factors in (0, 1].  Empty (the default) = no slip, gamma = 1.
        See :meth:`slip` and :meth:`.membrane.MembraneModel.edge_stretch`.
    experimental_hv_prestretch, experimental_hv_voltage : tuple of float
        The high voltage [V] the paper's experiments applied at each pre-stretch
        (section 5.1): 2730 V at lp = 1.10 and 2300 V at lp = 1.20, chosen there for a
        safe 80 V/um at the 15 mm stroke.  The HV of the figure 12-16 curves
        (``dea-twin study curves``), looked up by :meth:`experimental_hv`.  Not the
        section-6 study voltage, which is eq. 14 (:meth:`hv_voltage`).  Pre-stretches
        strictly increasing, in (1, 5]; voltages finite and > 0; empty = no
        experimental HV known.
    unit_modes : tuple of str
        Per unit ``"driven"`` (indenter position imposed, the characterisation rig),
        ``"free"`` (no indenter) or ``"biased"`` (the indenter rides on its bias
        element: an actuator unit).  One entry stands for every unit.
    bias : tuple of bias laws
        Bias element of each biased unit (:mod:`.bias`); YAML entries like
        ``{type: linear, stiffness: 40.0, free_position: 0.020}``, ``null`` = none.
        One entry stands for every unit.
    mass : tuple of float
        Moving mass of each biased unit's indenter and bias element [kg]; 0 (the
        default) = quasi-static.  One entry stands for every unit.
    damping : tuple of float
        Viscous damping of each biased unit's indenter [N s/m].  One entry for all.
    contact : tuple of bool
        Per unit, whether the indenter only pushes (unilateral contact): it lifts off
        when it would have to pull the membrane down, and the unit is free until the
        membrane comes back to it.  False (the default): the indenter is bonded.
    """

    layout: str = "array"
    rows: int = 1
    cols: int = 3
    length: float = 0.200
    width: float = 0.050
    frame_radius: float = 0.025
    electrode_diameter: float = 0.020
    spacing: float = 0.015
    indenter_radius: float = 0.0025
    electrode_shape: str = "circle"
    scale: float = 1.0
    thickness: float = 50e-6
    epsr: float = 2.8
    c10: float = 0.18e6
    c20: float = 10.84e3
    c30: float = -0.11e3
    prestretch: float = 1.10
    breakdown_field: float = 150e6
    element_order: int = 2
    mesh_size: float = 10e-3
    mesh_size_indenter: float = 1.25e-3
    mesh_size_electrode: float = 2.5e-3
    max_displacement: float = 0.030
    slip_displacement: tuple[float, ...] = ()
    slip_factor: tuple[float, ...] = ()
    experimental_hv_prestretch: tuple[float, ...] = (1.10, 1.20)
    experimental_hv_voltage: tuple[float, ...] = (2730.0, 2300.0)
    unit_modes: tuple[str, ...] = (DRIVEN,)
    bias: tuple[BiasLaw, ...] = (NoBias(),)
    mass: tuple[float, ...] = (0.0,)
    damping: tuple[float, ...] = (0.0,)
    contact: tuple[bool, ...] = (False,)

    def __post_init__(self) -> None:
        for name in _TABLES:  # accept any sequence of numbers
            object.__setattr__(self, name, _coerce(name, getattr(self, name), tuple))
        for name in UNIT_FIELDS:  # a scalar or a sequence, entries converted
            object.__setattr__(self, name, _coerce_units(name, getattr(self, name)))
        validate(self)
        for name in UNIT_FIELDS:  # one entry when every unit has the same: one config, one form
            values = getattr(self, name)
            if len(values) > 1 and all(v == values[0] for v in values):
                object.__setattr__(self, name, values[:1])

    # ---- derived quantities -------------------------------------------------------
    @property
    def n_units(self) -> int:
        """Number of DE units."""
        return 1 if self.layout == "circular" else self.rows * self.cols

    @property
    def yeoh(self) -> Yeoh:
        """The Yeoh coefficients as a :class:`Yeoh`."""
        return Yeoh(self.c10, self.c20, self.c30)

    @property
    def permittivity(self) -> float:
        """Absolute permittivity eps0 epsr [F/m]."""
        return EPS0 * self.epsr

    def scaled(self, name: str) -> float:
        """A length field multiplied by ``scale`` [m]."""
        return getattr(self, name) * self.scale

    @property
    def pitch(self) -> float:
        """Centre-to-centre distance of neighbouring units [m, scaled]."""
        return (self.electrode_diameter + self.spacing) * self.scale

    @property
    def square_side(self) -> float:
        """Side of the square electrode of the same area as the circle [m, scaled]."""
        return math.sqrt(math.pi) * 0.5 * self.electrode_diameter * self.scale

    def hv_voltage(self, critical_field: float = 80e6) -> float:
        """Paper eq. 14: ``V = Ec t0 / lp^2`` [V], flat-state field = ``critical_field``."""
        return critical_field * self.thickness / self.prestretch**2

    def experimental_hv(self) -> float:
        """The experiments' HV [V] at this config's pre-stretch (paper section 5.1).

        Raises
        ------
        ConfigError
            If ``prestretch`` is not in ``experimental_hv_prestretch`` (to 1e-9): the
            paper gives no rule between its two pre-stretches, so none is invented.
        """
        for lp, volt in zip(self.experimental_hv_prestretch, self.experimental_hv_voltage):
            if abs(lp - self.prestretch) <= 1e-9:
                return volt
        raise ConfigError(f"experimental_hv_prestretch: no experimental HV for prestretch {self.prestretch:g} "
                          f"(the table lists {list(self.experimental_hv_prestretch)}); add it to the table or "
                          "use the eq. 14 voltage")

    def slip(self, displacement: float) -> float:
        """Slip factor gamma(d) of eq. 11.

        Parameters
        ----------
        displacement : float
            Indenter displacement d [m, scaled, as commanded].

        Returns
        -------
        float
            gamma [-]: linear interpolation of the ``slip_factor`` table over
            ``slip_displacement * scale``, constant beyond its ends; 1.0 without a
            table.
        """
        if not self.slip_factor:
            return 1.0
        knots = np.asarray(self.slip_displacement) * self.scale
        return float(np.interp(displacement, knots, self.slip_factor))

    def per_unit(self, name: str) -> tuple:
        """A per-unit field (:data:`UNIT_FIELDS`) with one entry per unit (a single entry repeated)."""
        values = getattr(self, name)
        return values * self.n_units if len(values) == 1 else values

    @property
    def modes(self) -> tuple[str, ...]:
        """``unit_modes`` with one entry per unit."""
        return self.per_unit("unit_modes")

    def replace(self, **changes: Any) -> "ArrayConfig":
        """A copy with ``changes`` applied (validated)."""
        return dataclasses.replace(self, **changes)

    def to_dict(self) -> dict[str, Any]:
        """Plain dict of every field (for YAML, ROS parameters, MCAP metadata); tables as lists.

        ``bias`` is a list of YAML entries (``{type: linear, stiffness: ..., ...}``)."""
        out = {}
        for f in dataclasses.fields(self):
            value = getattr(self, f.name)
            if f.name == "bias":
                value = [law.to_dict() for law in value]
            out[f.name] = list(value) if isinstance(value, tuple) else value
        return out

    @classmethod
    def from_dict(cls, values: dict[str, Any]) -> "ArrayConfig":
        """Build a config from a dict, rejecting unknown keys by name."""
        known = {f.name for f in dataclasses.fields(cls)}
        unknown = sorted(set(values) - known)
        if unknown:
            raise ConfigError(f"unknown config field(s) {unknown}; known fields: {sorted(known)}")
        typed = {}
        for f in dataclasses.fields(cls):
            if f.name in values and f.name not in UNIT_FIELDS:
                typed[f.name] = _coerce(f.name, values[f.name], type(getattr(cls(), f.name)))
            elif f.name in values:
                typed[f.name] = values[f.name]  # converted by __post_init__
        return cls(**typed)


def _coerce_units(name: str, value: Any) -> tuple:
    """A per-unit field from a scalar, a mapping (``bias``) or a sequence, each entry converted.

    ``unit_modes`` entries are strings, ``bias`` entries bias laws (from YAML mappings or
    ``None``), ``mass``/``damping`` numbers, ``contact`` booleans.
    """
    single = (isinstance(value, (str, bytes, dict)) or value is None or not hasattr(value, "__iter__")
              or (name == "bias" and not isinstance(value, (list, tuple))))
    entries = (value,) if single else tuple(value)
    if not entries:
        raise ConfigError(f"{name}: needs one entry for every unit or one per unit, got an empty list")
    out = []
    for i, entry in enumerate(entries):
        label = f"{name}[{i}]"
        if name == "unit_modes":
            if not isinstance(entry, str):
                raise ConfigError(f"{label}: expected one of {list(MODES)}, got {entry!r}")
            out.append(entry)
        elif name == "bias":
            try:
                out.append(bias_from_entry(entry))
            except ValueError as exc:
                raise ConfigError(f"{label}: {exc}") from None
        elif name == "contact":
            if not isinstance(entry, (bool, np.bool_)):
                raise ConfigError(f"{label}: expected true or false, got {entry!r}")
            out.append(bool(entry))
        else:
            out.append(_coerce(label, entry, float))
    return tuple(out)


def _coerce(name: str, value: Any, kind: type) -> Any:
    """Convert a YAML/ROS value to the field's type or say which field is wrong.

    Table fields (tuples) take any sequence of numbers (a YAML list, a ROS double
    array) and become tuples of float.
    """
    if kind is tuple:
        if isinstance(value, (str, bytes, dict)) or not hasattr(value, "__iter__"):
            raise ConfigError(f"{name}: expected a list of numbers, got {value!r}")
        return tuple(_coerce(f"{name}[{i}]", v, float) for i, v in enumerate(value))
    if kind is bool or isinstance(value, bool):
        raise ConfigError(f"{name}: expected a {kind.__name__}, got {value!r}")
    try:
        if kind is int:
            if float(value) != int(value):
                raise ValueError
            return int(value)
        if kind is float:
            return float(value)
        if kind is str:
            if not isinstance(value, str):
                raise ValueError
            return value
    except (TypeError, ValueError):
        raise ConfigError(f"{name}: expected a {kind.__name__}, got {value!r}") from None
    return value


def _require(ok: bool, name: str, message: str) -> None:
    if not ok:
        raise ConfigError(f"{name}: {message}")


def validate(cfg: ArrayConfig) -> None:
    """Raise :class:`ConfigError` naming the first field outside its allowed range."""
    _require(cfg.layout in LAYOUTS, "layout", f"must be one of {LAYOUTS}, got {cfg.layout!r}")
    _require(cfg.electrode_shape in SHAPES, "electrode_shape", f"must be one of {SHAPES}, got {cfg.electrode_shape!r}")
    for name in ("rows", "cols"):
        _require(1 <= getattr(cfg, name) <= 64, name, f"must be an integer in [1, 64], got {getattr(cfg, name)}")
    positive = ("length", "width", "frame_radius", "electrode_diameter", "indenter_radius", "scale",
                "thickness", "mesh_size", "mesh_size_indenter", "mesh_size_electrode", "max_displacement",
                "breakdown_field")
    for name in positive:
        value = getattr(cfg, name)
        _require(math.isfinite(value) and value > 0, name, f"must be a finite number > 0, got {value}")
    _require(math.isfinite(cfg.spacing) and cfg.spacing > 0, "spacing",
             f"electrodes would overlap or touch: spacing must be > 0 m, got {cfg.spacing}")
    _require(1.0 <= cfg.epsr <= 1e4, "epsr", f"must be in [1, 1e4], got {cfg.epsr}")
    _require(cfg.c10 > 0, "c10", f"must be > 0 Pa (initial shear modulus 2 c10), got {cfg.c10}")
    _require(math.isfinite(cfg.c20) and math.isfinite(cfg.c30), "c20/c30", "must be finite")
    _require(1.0 < cfg.prestretch <= 5.0, "prestretch",
             f"must be in (1, 5]: a membrane at lp <= 1 is slack, got {cfg.prestretch}")
    _validate_slip(cfg)
    _validate_units(cfg)
    _validate_experimental_hv(cfg)
    _require(cfg.element_order in (1, 2), "element_order", f"must be 1 or 2, got {cfg.element_order}")
    for name in ("mesh_size_indenter", "mesh_size_electrode"):
        _require(getattr(cfg, name) <= cfg.mesh_size, name,
                 f"must be <= mesh_size ({cfg.mesh_size}), got {getattr(cfg, name)}")
    half = 0.5 * cfg.electrode_diameter
    inner = half if cfg.electrode_shape == "circle" else 0.5 * math.sqrt(math.pi) * half
    _require(cfg.indenter_radius < inner, "indenter_radius",
             f"must be smaller than the electrode's inscribed radius {inner} m, got {cfg.indenter_radius}")
    _require(cfg.mesh_size_indenter <= cfg.indenter_radius, "mesh_size_indenter",
             f"must be <= indenter_radius ({cfg.indenter_radius} m) to resolve the indenter")
    if cfg.layout == "circular":
        outer = half if cfg.electrode_shape == "circle" else half * math.sqrt(math.pi / 2.0)
        _require(cfg.frame_radius > outer, "frame_radius",
                 f"the electrode (outer radius {outer} m) must lie inside the frame, got {cfg.frame_radius}")
        return
    pitch = cfg.electrode_diameter + cfg.spacing
    for name, count, size in (("length", cfg.cols, cfg.length), ("width", cfg.rows, cfg.width)):
        extent = (count - 1) * pitch + cfg.electrode_diameter
        _require(extent < size, name,
                 f"{count} electrode(s) span {extent} m, which does not fit inside the frame ({size} m)")


def _validate_slip(cfg: ArrayConfig) -> None:
    """Check the eq. 11 table: equal lengths, displacements increasing, factors in (0, 1].

    Factors are capped at 1 because slip only lets the membrane creep inwards from
    the clamp (eq. 11 reduces the pre-stretch); above 0 so that the frame's X
    stretch ``1 + (lp - 1) gamma`` stays > 1 and the membrane taut at the frame.
    """
    disp, factor = cfg.slip_displacement, cfg.slip_factor
    _require(len(disp) == len(factor), "slip_factor",
             f"needs one factor per slip_displacement entry ({len(disp)}), got {len(factor)}")
    _require(all(math.isfinite(v) and v >= 0 for v in disp), "slip_displacement",
             f"must be finite and >= 0 m, got {list(disp)}")
    _require(all(b > a for a, b in zip(disp, disp[1:])), "slip_displacement",
             f"must be strictly increasing, got {list(disp)}")
    _require(all(math.isfinite(v) and 0 < v <= 1 for v in factor), "slip_factor",
             f"must be in (0, 1] (slip only reduces the frame's pre-stretch), got {list(factor)}")


def _validate_experimental_hv(cfg: ArrayConfig) -> None:
    """Check the experimental HV table: equal lengths, pre-stretches increasing in (1, 5], voltages > 0."""
    stretches, volts = cfg.experimental_hv_prestretch, cfg.experimental_hv_voltage
    _require(len(stretches) == len(volts), "experimental_hv_voltage",
             f"needs one voltage per experimental_hv_prestretch entry ({len(stretches)}), got {len(volts)}")
    _require(all(math.isfinite(v) and 1.0 < v <= 5.0 for v in stretches), "experimental_hv_prestretch",
             f"must be in (1, 5], got {list(stretches)}")
    _require(all(b > a for a, b in zip(stretches, stretches[1:])), "experimental_hv_prestretch",
             f"must be strictly increasing, got {list(stretches)}")
    _require(all(math.isfinite(v) and v > 0 for v in volts), "experimental_hv_voltage",
             f"must be finite and > 0 V, got {list(volts)}")


def _validate_units(cfg: ArrayConfig) -> None:
    """Per-unit fields: one entry or one per unit; modes known; mass and damping finite and >= 0."""
    n = cfg.n_units
    for name in UNIT_FIELDS:
        count = len(getattr(cfg, name))
        _require(count in (1, n), name, f"needs 1 entry (for every unit) or {n} (one per unit), got {count}")
    for i, mode in enumerate(cfg.unit_modes):
        _require(mode in MODES, f"unit_modes[{i}]", f"must be one of {list(MODES)}, got {mode!r}")
    for name in ("mass", "damping"):
        for i, value in enumerate(getattr(cfg, name)):
            _require(math.isfinite(value) and value >= 0, f"{name}[{i}]",
                     f"must be a finite number >= 0 ({'kg' if name == 'mass' else 'N s/m'}), got {value}")

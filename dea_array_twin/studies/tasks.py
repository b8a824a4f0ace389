"""The paper's studies: figure 12-16 curves, coupling indices (section 6) and parameter sweeps.

Everything here is a pure function of an :class:`ArrayConfig`: a study is a list of
independent :class:`CurveTask` s, each solved from the flat state by a fresh twin
(:func:`run_curve`), so any executor (a loop, local processes, a Dask cluster) gives
the same numbers.  Indices and sweep tables are computed from the curves afterwards.

Coupling indices (eqs. 13, 15, 16), for the measured unit m (the central one) and its
neighbour on the left:

* ``eta_F,LV = 100 (Fmax_default - Fmax_perturbed) / Fmax_default`` with unit m swept
  to 0.75 D at 0 V; *default*: the other units not deflected (free, or held at 0 m
  with ``undeflected=0.0``), *perturbed*: every other unit driven, pre-deflected to 0.4 D.
* ``eta_F,HV``: the same with ``V = Ec t0 / lp^2`` (eq. 14, Ec = 80 V/um) on unit m.
* ``eta_C = 100 dCmax(neighbour swept) / dCmax(m swept)``: capacitance change of unit
  m when its neighbour, resp. unit m itself, is swept to 0.75 D at 0 V, others not
  deflected.  ``dCmax`` is the largest-magnitude change along the curve, with its sign.

Figures 12-16 (section 5) are the experiments' curves: each of the neighbour and the
central unit swept to 15 mm with the other units free or pre-deflected by 4, 6 or 8 mm,
at 0 V and at the experiments' HV (``ArrayConfig.experimental_hv``).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Callable, Sequence

import numpy as np

from ..model.config import ArrayConfig, ConfigError
from ..model.geometry import edge_distance
from ..model.membrane import DRIVEN, FREE
from ..model.solver import ConvergenceError, NewtonSettings
from ..model.twin import ArrayTwin, TwinResult

#: Field strength of air at breakdown used by the paper for the minimum spacing [V/m].
AIR_BREAKDOWN_FIELD = 3e6
#: Eq. 14's flat-state field [V/m].
CRITICAL_FIELD = 80e6
#: Sweep stroke and neighbour pre-deflection, as fractions of D (section 6.1).
STROKE, PRE_DEFLECTION = 0.75, 0.4
#: The experiments' neighbour pre-deflections (section 5.1: 4, 6 and 8 mm with D = 20 mm), fractions of D.
PRE_LOADS = (0.2, 0.3, 0.4)


@dataclass(frozen=True)
class CurveTask:
    """One curve: a fresh twin of ``config``, neighbours set, ``swept`` moved 0 -> ``stroke``.

    Attributes
    ----------
    config : ArrayConfig
        The array.
    swept : int
        The unit moved, 0-based.
    neighbours : float or None
        ``None``: every other unit free; else every other unit driven at this
        displacement [m] (applied at 0 V before the sweep).
    voltage : float
        Voltage on the swept unit [V] (the others stay at 0 V), applied at d = 0.
    stroke : float
        Final displacement of the swept unit [m].
    steps : int
        Equal displacement steps (``steps + 1`` points, 0 included).
    key : tuple
        The task's place in its study (e.g. ``("spacing", 0.001, "lv_default")``).
    """

    config: ArrayConfig
    swept: int
    neighbours: float | None
    voltage: float
    stroke: float
    steps: int
    key: tuple = ()


@dataclass(frozen=True)
class CurveResult:
    """The solved curve of a :class:`CurveTask` (SI units; per point and unit).

    Attributes
    ----------
    task : CurveTask
        What was solved.
    displacement : ndarray, shape (k,)
        Swept unit's displacement [m].
    force, capacitance : ndarray, shape (k, n)
        Per point and unit [N], [F].
    delta_capacitance : ndarray, shape (k, n)
        Capacitance change from the first point, the start of the test (after the
        neighbours' pre-deflection and with the voltage on) [F]: the paper's
        "capacitance deviation from the initial value".  For a test that starts from
        the flat state at 0 V this is the change from the flat pre-stretched state.
    peak_field : ndarray, shape (k, n)
        Largest true electric field on each electrode [V/m].
    min_principal_stress : ndarray, shape (k,)
        Smallest principal Cauchy stress outside held disks [Pa].
    wrinkled, field_exceeded : ndarray of bool, shape (k,)
        Compressive stress (wrinkling, not represented by the model) / field above
        the breakdown limit, as the solver reported them.
    stable : ndarray of bool, shape (k,)
        Tangent positive definite at the point.
    """

    task: CurveTask
    displacement: np.ndarray
    force: np.ndarray
    capacitance: np.ndarray
    delta_capacitance: np.ndarray
    peak_field: np.ndarray
    min_principal_stress: np.ndarray
    wrinkled: np.ndarray
    field_exceeded: np.ndarray
    stable: np.ndarray


#: :class:`CurveResult` fields stacked point by point from the
#: :class:`~dea_array_twin.model.twin.TwinResult` fields of the same name.
_STACKED = ("force", "capacitance", "peak_field", "min_principal_stress", "wrinkled", "field_exceeded")


def run_curve(task: CurveTask, on_point: Callable[[float, TwinResult], None] | None = None) -> CurveResult:
    """Solve a :class:`CurveTask` from the flat state (deterministic, no shared state).

    ``on_point(d, result)``, if given, is called after each point (progress,
    warnings): side effects stay out of the loop.

    Raises
    ------
    ConvergenceError
        If a point has no equilibrium.
    """
    twin = ArrayTwin(task.config, NewtonSettings(check_stability=True))
    n, k = twin.n_units, task.swept
    others = np.arange(n) != k
    modes = [DRIVEN if (i == k or task.neighbours is not None) else FREE for i in range(n)]
    base = np.where(others, 0.0 if task.neighbours is None else task.neighbours, 0.0)
    voltage = np.where(others, 0.0, task.voltage)
    if task.neighbours is not None:  # pre-deflect the neighbours at 0 V first
        twin.solve(base, np.zeros(n), modes)
    displacement = np.linspace(0.0, task.stroke, task.steps + 1)
    rows = []
    for d in displacement:
        rows.append(twin.solve(np.where(others, base, d), voltage, modes))
        if on_point is not None:
            on_point(float(d), rows[-1])
    stacked = {name: np.array([getattr(r, name) for r in rows]) for name in _STACKED}
    return CurveResult(task=task, displacement=displacement, stable=np.array([r.stable is not False for r in rows]),
                       delta_capacitance=stacked["capacitance"] - stacked["capacitance"][0], **stacked)



# --------------------------------------------------------------------- coupling

def measured_units(cfg: ArrayConfig) -> tuple[int, int]:
    """The measured (central) unit and the neighbour swept for eta_C, 0-based.

    The central unit is the one nearest the middle of the grid; its neighbour is the
    next unit in its row (to the left if there is one, else to the right), or in a
    single column the next unit in the column (above, else below).

    Raises
    ------
    ConfigError
        For a layout with a single unit.
    """
    if cfg.layout != "array" or cfg.n_units < 2:
        raise ConfigError("layout: coupling studies need an 'array' layout with at least two units")
    row, col = (cfg.rows - 1) // 2, cfg.cols // 2
    centre = row * cfg.cols + col
    if cfg.cols > 1:
        return centre, centre - 1 if col > 0 else centre + 1
    return centre, centre - cfg.cols if row > 0 else centre + cfg.cols


COUPLING_CASES = ("lv_default", "lv_perturbed", "hv_default", "hv_perturbed", "c_neighbour")


def coupling_tasks(cfg: ArrayConfig, steps: int = 15, key: tuple = (), undeflected: float | None = None,
                   hv: float | None = None) -> list[CurveTask]:
    """The five curves behind eqs. 13, 15 and 16 for ``cfg`` (keys ``key + (case,)``).

    Parameters
    ----------
    undeflected : float or None
        The paper's "neighbours not deflected": ``None`` (default) free units, or
        indenters held at this displacement [m] (``0.0``: held flat).
    hv : float, optional
        The HV on the measured unit [V]; default eq. 14, ``cfg.hv_voltage(80 V/um)``.
    """
    centre, neighbour = measured_units(cfg)
    diameter = cfg.scaled("electrode_diameter")
    stroke, pre = STROKE * diameter, PRE_DEFLECTION * diameter
    hv = cfg.hv_voltage(CRITICAL_FIELD) if hv is None else hv
    spec = {"lv_default": (centre, undeflected, 0.0), "lv_perturbed": (centre, pre, 0.0),
            "hv_default": (centre, undeflected, hv), "hv_perturbed": (centre, pre, hv),
            "c_neighbour": (neighbour, undeflected, 0.0)}
    return [CurveTask(cfg, swept, nb, volt, stroke, steps, key + (case,))
            for case, (swept, nb, volt) in spec.items()]


@dataclass(frozen=True)
class CouplingIndices:
    """Coupling indices (eqs. 13, 15, 16) of one configuration and what they come from.

    Attributes
    ----------
    eta_f_lv, eta_f_hv, eta_c : float
        The indices [%].
    f_max : dict
        Largest force of the measured unit per force case [N].
    dc_max_default, dc_max_perturbed : float
        Signed largest-magnitude capacitance change of the measured unit when it,
        resp. its neighbour, is swept [F].
    hv_voltage : float
        The HV on the measured unit [V] (eq. 14 unless the tasks chose another).
    wrinkled, field_exceeded, unstable : tuple of str
        The cases in which some point was flagged.
    """

    eta_f_lv: float
    eta_f_hv: float
    eta_c: float
    f_max: dict
    dc_max_default: float
    dc_max_perturbed: float
    hv_voltage: float
    wrinkled: tuple
    field_exceeded: tuple
    unstable: tuple


def largest(values: np.ndarray) -> float:
    """The entry of largest magnitude, with its sign (the paper's "maximum" of a dC curve)."""
    return float(values[np.argmax(np.abs(values))])


def coupling_indices(curves: dict[str, CurveResult]) -> CouplingIndices:
    """Eqs. 13, 15, 16 from the five curves of :func:`coupling_tasks`, keyed by case."""
    some = curves["lv_default"]
    centre, _ = measured_units(some.task.config)
    f_max = {case: float(curves[case].force[:, centre].max()) for case in COUPLING_CASES[:4]}

    def eta(kind: str) -> float:
        default, perturbed = f_max[f"{kind}_default"], f_max[f"{kind}_perturbed"]
        return 100.0 * (default - perturbed) / default

    dc_default = largest(curves["lv_default"].delta_capacitance[:, centre])
    dc_perturbed = largest(curves["c_neighbour"].delta_capacitance[:, centre])
    return CouplingIndices(
        eta_f_lv=eta("lv"), eta_f_hv=eta("hv"), eta_c=100.0 * dc_perturbed / dc_default, f_max=f_max,
        dc_max_default=dc_default, dc_max_perturbed=dc_perturbed,
        hv_voltage=curves["hv_default"].task.voltage,
        wrinkled=tuple(c for c in COUPLING_CASES if curves[c].wrinkled.any()),
        field_exceeded=tuple(c for c in COUPLING_CASES if curves[c].field_exceeded.any()),
        unstable=tuple(c for c in COUPLING_CASES if not curves[c].stable.all()))


# ----------------------------------------------------------------------- sweeps

@dataclass(frozen=True)
class Sweep:
    """One parameter study of section 6: how a value maps to a configuration.

    Attributes
    ----------
    name : str
        CLI name.
    parameter : str
        What varies, with its unit (CSV column name).
    values : tuple of float
        The paper's range [SI].
    geometry : str
        How the geometry changes with the parameter (for the CSV header and docs).
    apply : callable
        ``apply(base, value) -> ArrayConfig``.
    """

    name: str
    parameter: str
    values: tuple
    geometry: str
    apply: Callable[[ArrayConfig, float], ArrayConfig]


def _row_extent(cfg: ArrayConfig, count: int) -> float:
    """Reference span [m, unscaled] of ``count`` electrodes in a row or column."""
    return (count - 1) * (cfg.electrode_diameter + cfg.spacing) + cfg.electrode_diameter


def _with_edge_distance(base: ArrayConfig, b: float) -> ArrayConfig:
    return base.replace(width=_row_extent(base, base.rows) + 2.0 * b)


SWEEPS: dict[str, Sweep] = {s.name: s for s in (
    Sweep("spacing", "spacing_m", tuple(np.round(np.arange(1.0, 15.1, 2.5) * 1e-3, 6)) + (0.015,),
          "electrode gap d varies; D, r, L and H are fixed, so the distance to the long edges "
          "b = (H - D)/2 stays 15 mm and the row stays centred: the distance to the short edges is "
          "(L - 3D - 2d)/2", lambda base, v: base.replace(spacing=v)),
    Sweep("edge_distance", "edge_distance_m", tuple(np.round(np.arange(10.0, 50.1, 5.0) * 1e-3, 6)),
          "distance b from the electrodes to the long edges varies through the frame width, H = D + 2b "
          "(rows x pitch - d + 2b in general); L, D, d and r are fixed (the short edges stay 55 mm away, "
          "so b remains the smallest electrode-to-frame distance)", _with_edge_distance),
    Sweep("prestretch", "prestretch", tuple(np.round(np.arange(1.10, 1.801, 0.05), 4)),
          "equi-biaxial pre-stretch lp varies; the reference (unstretched) geometry is fixed, so the "
          "stretched array grows with lp, and the HV voltage follows eq. 14, V = Ec t0 / lp^2",
          lambda base, v: base.replace(prestretch=v)),
    Sweep("scale", "downscale_factor", (1.0, 2.0, 5.0, 10.0, 13.0, 14.0, 20.0, 50.0, 100.0),
          "every in-plane length (L, H, D, d, r, hence b) is divided by the factor k (config scale = 1/k); "
          "t0, lp and so the eq. 14 voltage are unchanged; the gap d/k falls below the air breakdown "
          "distance V / (3 kV/mm) beyond k = d / (V / 3 kV/mm)",
          lambda base, v: base.replace(scale=base.scale / v)),
)}

SHAPE_GEOMETRY = ("circle vs square of equal area: side s = sqrt(pi) D / 2 = 0.886 D, same centres, so the "
                  "gap between squares is d + D - s; unit 2 swept to 0.75 D with its neighbours free, at 0 V "
                  "and at the eq. 14 voltage")


def sweep_tasks(sweep: Sweep, base: ArrayConfig, values: Sequence[float] | None = None,
                steps: int = 15, undeflected: float | None = None) -> list[CurveTask]:
    """The coupling curves of every value of ``sweep`` (keys ``(sweep.name, value, case)``).

    ``undeflected`` is passed to :func:`coupling_tasks` (None: free neighbours).

    Raises
    ------
    ConfigError
        If a value gives an invalid array (the message names the value).
    """
    tasks = []
    for value in values if values is not None else sweep.values:
        if not (math.isfinite(value) and value > 0):
            raise ConfigError(f"{sweep.name} = {value}: sweep values must be finite and > 0")
        try:
            cfg = sweep.apply(base, float(value))
        except ConfigError as exc:
            raise ConfigError(f"{sweep.name} = {value}: {exc}") from None
        tasks += coupling_tasks(cfg, steps, (sweep.name, float(value)), undeflected)
    return tasks


def shape_tasks(base: ArrayConfig, steps: int = 15) -> list[CurveTask]:
    """Central unit swept to 0.75 D, neighbours free, circle and square, LV and HV."""
    tasks = []
    for shape in ("circle", "square"):
        cfg = base.replace(electrode_shape=shape)
        centre, _ = measured_units(cfg)
        stroke = STROKE * cfg.scaled("electrode_diameter")
        for case, volt in (("lv", 0.0), ("hv", cfg.hv_voltage(CRITICAL_FIELD))):
            tasks.append(CurveTask(cfg, centre, None, volt, stroke, steps, ("shape", shape, case)))
    return tasks


def figure_units(cfg: ArrayConfig) -> tuple[int, ...]:
    """The units of figures 12-16, 0-based: the eta_C neighbour and the central unit, in order.

    For the paper's 1-by-3 row these are DE1 and DE2 (DE3 mirrors DE1); a single-unit
    layout has just its unit.
    """
    if cfg.n_units == 1:
        return (0,)
    return tuple(sorted(measured_units(cfg)))


def curves_tasks(base: ArrayConfig, steps: int = 15, stroke: float | None = None,
                 neighbours: Sequence[float | None] | None = None,
                 voltages: Sequence[float] | None = None) -> list[CurveTask]:
    """Figures 12-16 at ``base``'s pre-stretch: each :func:`figure_units` unit swept in turn.

    Keys are ``("curves", lp, "unit k, neighbours ..., V")``.

    Parameters
    ----------
    stroke : float, optional
        Final displacement [m]; default 0.75 D (the experiments' 15 mm).
    neighbours : sequence, optional
        Per setting, ``None`` (the other units free) or their pre-deflection [m]
        (``0.0``: held flat).  Default: free, then 0.2, 0.3 and 0.4 D (the paper's
        "0 mm" read as not deflected, then 4, 6 and 8 mm).
    voltages : sequence of float, optional
        Voltages on the swept unit [V]; default 0 and ``base.experimental_hv()``.

    Raises
    ------
    ConfigError
        Default voltages and no experimental HV for ``base.prestretch``.
    """
    diameter = base.scaled("electrode_diameter")
    stroke = STROKE * diameter if stroke is None else stroke
    voltages = [0.0, base.experimental_hv()] if voltages is None else voltages
    settings = [None, *(f * diameter for f in PRE_LOADS)] if neighbours is None else list(neighbours)
    if base.n_units == 1:  # no neighbours to set
        settings = [None]
    return [CurveTask(base, k, nb, v, stroke, steps,
                      ("curves", base.prestretch, f"unit {k + 1}, neighbours {neighbour_label(nb)}, {v:g} V"))
            for k in figure_units(base) for nb in settings for v in voltages]


def neighbour_label(setting: float | None) -> str:
    """``"free"`` or the pre-deflection in mm (``"held at 0 mm"`` for 0), for labels and tables."""
    if setting is None:
        return "free"
    return "held at 0 mm" if setting == 0 else f"at {setting * 1e3:g} mm"


def geometry_row(cfg: ArrayConfig) -> dict[str, float]:
    """The geometry a sweep point actually ran with [m, scaled], for tables."""
    return {"L_m": cfg.scaled("length"), "H_m": cfg.scaled("width"), "D_m": cfg.scaled("electrode_diameter"),
            "d_m": cfg.scaled("spacing"), "b_m": edge_distance(cfg), "r_m": cfg.scaled("indenter_radius"),
            "prestretch": cfg.prestretch, "hv_voltage_V": cfg.hv_voltage(CRITICAL_FIELD)}


def air_breakdown_gap(cfg: ArrayConfig) -> float:
    """Smallest gap [m] that holds the eq. 14 voltage in air (3 kV/mm)."""
    return cfg.hv_voltage(CRITICAL_FIELD) / AIR_BREAKDOWN_FIELD


def shape_difference(circle: CurveResult, square: CurveResult) -> tuple[float, float]:
    """Largest difference of the measured unit's force and dC curves, relative to their maxima."""
    k = circle.task.swept
    rel = []
    for name in ("force", "delta_capacitance"):
        a, b = getattr(circle, name)[:, k], getattr(square, name)[:, k]
        scale = max(np.abs(a).max(), np.abs(b).max())
        rel.append(float(np.abs(a - b).max() / scale) if scale > 0 else math.nan)
    return rel[0], rel[1]


# ------------------------------------------------------------------ collecting

@dataclass(frozen=True)
class CurveFailure:
    """A curve the solver could not finish, and why."""

    task: CurveTask
    message: str


def try_curve(task: CurveTask) -> CurveResult | CurveFailure:
    """:func:`run_curve`, with a solver failure returned instead of raised (a sweep goes on)."""
    try:
        return run_curve(task)
    except ConvergenceError as exc:
        return CurveFailure(task, str(exc))


def index_rows(results: Sequence[CurveResult | CurveFailure]) -> list[dict]:
    """One table row per configuration: geometry, the three indices and their flags.

    ``results`` are the curves of :func:`coupling_tasks` / :func:`sweep_tasks`, keyed
    ``(..., case)``; rows come in first-seen order.  A configuration with a failed
    curve gets NaN indices and the solver's message in ``error``.
    """
    groups: dict[tuple, dict[str, CurveResult | CurveFailure]] = {}
    for res in results:
        groups.setdefault(res.task.key[:-1], {})[res.task.key[-1]] = res
    rows = []
    for key, curves in groups.items():
        cfg = next(iter(curves.values())).task.config
        row = {"study": key[0] if key else "coupling", "value": key[1] if len(key) > 1 else math.nan,
               **geometry_row(cfg), "air_gap_min_m": air_breakdown_gap(cfg)}
        failed = [c for c in curves.values() if isinstance(c, CurveFailure)]
        if failed:
            row.update(eta_f_lv=math.nan, eta_f_hv=math.nan, eta_c=math.nan,
                       error="; ".join(f"{f.task.key[-1]}: {f.message}" for f in failed))
        else:
            ci = coupling_indices(curves)  # type: ignore[arg-type]
            row.update(eta_f_lv=ci.eta_f_lv, eta_f_hv=ci.eta_f_hv, eta_c=ci.eta_c,
                       **{f"f_max_{case}_N": v for case, v in ci.f_max.items()},
                       dc_max_default_F=ci.dc_max_default, dc_max_perturbed_F=ci.dc_max_perturbed,
                       wrinkled=" ".join(ci.wrinkled), field_exceeded=" ".join(ci.field_exceeded),
                       unstable=" ".join(ci.unstable), error="")
        row["below_air_breakdown"] = row["d_m"] < row["air_gap_min_m"]
        rows.append(row)
    return rows

"""Figures 5 and 6 of the paper, computed: the stroke of a unit on an LBS and on an NBS.

Section 3.2 of the paper: an NBS (negative-rate bias spring) matched to the nominal
force curves of the central unit (neighbours not deflected, figure 5) gives a much larger
stroke than an LBS (linear positive-rate spring); with the neighbours pre-deflected
(figure 6) the unit's curves change and the NBS loses much of its stroke.  Here:

1. the measured unit's driven force curves at 0 V and at the HV (the experiments' voltage
   at the config's pre-stretch, :meth:`~dea_array_twin.model.config.ArrayConfig.experimental_hv`:
   2730 V at lp = 1.10), neighbours free and pre-deflected by 0.4 D
   (:class:`~.tasks.CurveTask`, so any executor runs them);
2. both biases designed on the *nominal* curves (:func:`match_biases`), the way a
   designer does it graphically: both pass through the 0 V curve at the operating point
   ``w0``; the LBS ``B = k (x0 - w)`` is free at ``x0 = 2 w0``; the NBS ``B = k (x0 - w)``
   has the rate ``k = -rate_fraction * dF_HV/dw(w0)`` (a fraction of the membrane's
   softest stiffness over the stroke: the twin's curves stiffen with w, so every
   equilibrium from w0 up stays stable);
3. the stroke (position at HV minus position at 0 V) of the unit *biased* with each,
   neighbours free and pre-deflected, by full quasi-static biased solves
   (:func:`~dea_array_twin.model.response.stroke`), released at ``w0``.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable, Sequence

from scipy.interpolate import PchipInterpolator

from ..model.bias import LinearBias
from ..model.config import BIASED, DRIVEN, FREE, ArrayConfig
from ..model.response import stroke
from ..model.twin import ArrayTwin
from .tasks import PRE_DEFLECTION, STROKE, CurveFailure, CurveResult, CurveTask, measured_units

#: Default operating point at 0 V, as a fraction of D.
OPERATING_POINT = 0.25
#: Default NBS rate as a fraction of the nominal HV stiffness at the operating point.
RATE_FRACTION = 0.9
CASES = ("lv", "hv", "lv_pre", "hv_pre")


def stroke_curve_tasks(cfg: ArrayConfig, voltage: float | None = None, steps: int = 30) -> list[CurveTask]:
    """The measured unit's driven curves to 0.75 D: 0 V and ``voltage`` (default: the experiments' HV),
    neighbours free and at 0.4 D."""
    unit, _ = measured_units(cfg)
    voltage = cfg.experimental_hv() if voltage is None else voltage
    diameter = cfg.scaled("electrode_diameter")
    pre = PRE_DEFLECTION * diameter
    spec = {"lv": (None, 0.0), "hv": (None, voltage), "lv_pre": (pre, 0.0), "hv_pre": (pre, voltage)}
    return [CurveTask(cfg, unit, neighbours, volts, STROKE * diameter, steps, ("stroke", case))
            for case, (neighbours, volts) in spec.items()]


def match_biases(lv: CurveResult, hv: CurveResult, operating_point: float,
                 rate_fraction: float = RATE_FRACTION) -> dict[str, LinearBias]:
    """LBS and NBS through the nominal 0 V curve at ``operating_point`` [m] (see the module text).

    The curves are interpolated with PCHIP; the NBS rate is ``rate_fraction`` times the
    HV curve's slope there.
    """
    unit = lv.task.swept
    force = float(PchipInterpolator(lv.displacement, lv.force[:, unit])(operating_point))
    slope = float(PchipInterpolator(hv.displacement, hv.force[:, unit]).derivative()(operating_point))
    lbs = LinearBias(force / operating_point, 2.0 * operating_point)
    rate = -rate_fraction * slope
    return {"LBS": lbs, "NBS": LinearBias(rate, operating_point + force / rate)}


@dataclass(frozen=True)
class StrokeRow:
    """The stroke of the measured unit with one bias and one neighbour state (SI units)."""

    bias: str
    law: LinearBias
    neighbours: str
    rest_position: float
    position: float
    stroke: float
    stable: bool
    snap: bool


def bias_strokes(cfg: ArrayConfig, biases: dict[str, LinearBias], voltage: float, operating_point: float,
                 on_row: Callable[[StrokeRow], None] | None = None) -> list[StrokeRow]:
    """Stroke of the measured unit biased with each law, neighbours free ("free") and at 0.4 D ("pre")."""
    unit, _ = measured_units(cfg)
    n = cfg.n_units
    pre = PRE_DEFLECTION * cfg.scaled("electrode_diameter")
    rows = []
    for name, law in biases.items():
        for neighbours in ("free", "pre"):
            modes = [BIASED if k == unit else (FREE if neighbours == "free" else DRIVEN) for k in range(n)]
            twin = ArrayTwin(cfg.replace(unit_modes=tuple(modes), bias=(law,)))
            curve = stroke(twin, [voltage], unit, 0.0 if neighbours == "free" else pre, operating_point)
            rows.append(StrokeRow(name, law, neighbours, float(curve.rest.position[unit]),
                                  float(curve.position[0, unit]), float(curve.stroke[0, unit]),
                                  bool(curve.stable[0] and curve.rest.stable), bool(curve.snap[0])))
            if on_row is not None:
                on_row(rows[-1])
    return rows


@dataclass(frozen=True)
class StrokeStudy:
    """Figures 5-6: the curves, the two biases and the strokes."""

    curves: dict[str, CurveResult]
    biases: dict[str, LinearBias]
    rows: list[StrokeRow]
    voltage: float
    operating_point: float
    rate_fraction: float

    def row(self, bias: str, neighbours: str) -> StrokeRow:
        """The row of ``bias`` ("LBS", "NBS") with ``neighbours`` ("free", "pre")."""
        return next(r for r in self.rows if r.bias == bias and r.neighbours == neighbours)


def stroke_study(cfg: ArrayConfig, results: Sequence[CurveResult | CurveFailure],
                 operating_point: float | None = None, rate_fraction: float = RATE_FRACTION,
                 on_row: Callable[[StrokeRow], None] | None = None) -> StrokeStudy:
    """Design the biases on the solved :func:`stroke_curve_tasks` and compute the strokes.

    Raises
    ------
    ValueError
        A curve failed to solve.
    """
    failed = [r for r in results if isinstance(r, CurveFailure)]
    if failed:
        raise ValueError(f"curve {failed[0].task.key} failed: {failed[0].message}")
    curves = {r.task.key[-1]: r for r in results}
    voltage = curves["hv"].task.voltage
    w0 = OPERATING_POINT * cfg.scaled("electrode_diameter") if operating_point is None else operating_point
    biases = match_biases(curves["lv"], curves["hv"], w0, rate_fraction)
    rows = bias_strokes(cfg, biases, voltage, w0, on_row)
    return StrokeStudy(curves, biases, rows, voltage, w0, rate_fraction)


def stroke_summary(result: StrokeStudy) -> list[str]:
    """Markdown lines: the design and the table of strokes."""
    lines = ["## stroke (figures 5-6)", "",
             f"Operating point w0 = {1e3 * result.operating_point:g} mm at 0 V; HV = {result.voltage:g} V on the "
             f"measured unit; neighbours free or driven at 0.4 D.", ""]
    for name, law in result.biases.items():
        lines.append(f"- {name}: B = k (x0 - w), k = {law.stiffness:.2f} N/m, x0 = {1e3 * law.free_position:.3f} mm")
    lines += ["", "| bias | neighbours | w(0 V) [mm] | w(HV) [mm] | stroke [mm] | stable | snap |",
              "|---|---|---|---|---|---|---|"]
    for r in result.rows:
        lines.append(f"| {r.bias} | {r.neighbours} | {1e3 * r.rest_position:.3f} | {1e3 * r.position:.3f} "
                     f"| {1e3 * r.stroke:.3f} | {'yes' if r.stable else 'NO'} | {'yes' if r.snap else 'no'} |")
    nominal, perturbed = result.row("NBS", "free").stroke, result.row("NBS", "pre").stroke
    lbs = result.row("LBS", "free").stroke
    lines += ["", f"NBS/LBS stroke, neighbours free: {nominal / lbs:.2f}; NBS stroke with the neighbours "
                  f"pre-deflected: {100 * perturbed / nominal:.1f}% of nominal.", ""]
    return lines

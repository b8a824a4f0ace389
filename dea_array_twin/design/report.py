"""What a bias design writes: the design YAML, the strokes CSV and the summary.

* :func:`design_yaml`: the array's config with the array-aware design (every field, so
  ``dea-twin stroke design.yaml`` and :func:`~dea_array_twin.configfile.load_config` take
  it as it is; its ``unit_modes`` and ``bias`` are the design);
* :func:`stroke_rows` / :func:`write_strokes`: the stroke of every designed unit in
  every scenario, for the single-unit-tuned and the array-aware design, full biased
  solves next to the inner model's prediction;
* :func:`summary`: markdown lines: the settings, both designs, their smallest strokes
  and where the worst case is, and the comparison the paper's section 3.2 is about
  (single-unit nominal stroke, the same design in the array, the array-aware design).
"""

from __future__ import annotations

import csv
import math
from pathlib import Path

import yaml

from ..model.bias import BiasLaw
from .bias_design import BiasDesign, ScenarioResult, Verification

#: Columns of the strokes CSV (SI units).
STROKE_COLUMNS = ("design", "unit", "scenario", "low_position_m", "high_position_m", "stroke_m",
                  "predicted_stroke_m", "margin_N_per_m", "stable", "snapped", "hysteresis", "error")


def design_yaml(result: BiasDesign) -> str:
    """The config YAML of the array with the array-aware design."""
    head = (f"# Bias design by dea-twin design-bias: --bias {result.settings.family} --voltage "
            f"{result.settings.voltage:g} V, smallest stroke {1e3 * result.aware.verification.min_stroke:.4f} mm "
            f"over {len(result.scenarios)} scenarios (full biased solves).\n"
            f"# The scenarios release the indenters at {result.settings.start:g} m: dea-twin stroke --start "
            f"{result.settings.start:g} (an NBS can be bistable: the release height picks the branch).\n")
    return head + yaml.safe_dump(result.config.to_dict(), sort_keys=False)


def _row(name: str, r: ScenarioResult, predicted: float) -> dict:
    def at(state) -> float:
        return float(state.position[r.scenario.unit]) if state is not None else math.nan

    return {"design": name, "unit": r.scenario.unit + 1, "scenario": r.scenario.label,
            "low_position_m": at(r.low), "high_position_m": at(r.high), "stroke_m": r.stroke,
            "predicted_stroke_m": predicted, "margin_N_per_m": r.margin, "stable": r.stable,
            "snapped": r.snapped, "hysteresis": r.hysteresis, "error": r.error}


def stroke_rows(result: BiasDesign) -> list[dict]:
    """One row per design and scenario: see :data:`STROKE_COLUMNS`.

    ``design`` is ``single-alone`` (the single-unit-tuned design on each unit alone, the
    other units free: its nominal scenario), ``single`` (that design on every designed
    unit of the array) or ``aware`` (the array-aware design).

    ``scenario`` is one character per unit: ``s`` the stroking unit, ``V`` a unit at the
    voltage, ``0`` one at 0 V.  ``predicted_stroke_m`` is the inner model's stroke of the
    array-aware design (NaN for the single-unit design, which was optimised on the
    nominal curves only)."""
    rows = [_row("single-alone", r, math.nan) for r in result.single_nominal.rows]
    rows += [_row("single", r, math.nan) for r in result.single.verification.rows]
    rows += [_row("aware", r, float(p)) for r, p in zip(result.aware.verification.rows, result.aware.predicted)]
    return rows


def write_strokes(result: BiasDesign, path: Path) -> Path:
    """The strokes CSV (:func:`stroke_rows`)."""
    with open(path, "w", newline="") as fh:
        writer = csv.DictWriter(fh, fieldnames=STROKE_COLUMNS)
        writer.writeheader()
        writer.writerows(stroke_rows(result))
    return path


def _law_text(law: BiasLaw) -> str:
    entry = law.to_dict()
    if entry["type"] == "linear":
        return f"linear: k = {entry['stiffness']:.4g} N/m, x0 = {1e3 * entry['free_position']:.4f} mm"
    if entry["type"] == "table":
        return (f"table of {len(entry['position'])} points over [{1e3 * entry['position'][0]:.3f}, "
                f"{1e3 * entry['position'][-1]:.3f}] mm, B in [{min(entry['force']):.4g}, {max(entry['force']):.4g}] N")
    return " + ".join(f"({_law_text(t)})" for t in law.terms) if entry["type"] == "sum" else str(entry)


def _worst(verification: Verification) -> str:
    w = verification.worst
    where = f"unit {w.scenario.unit + 1} in scenario {w.scenario.label}"
    if not math.isfinite(w.stroke):
        return f"{where}: no equilibrium ({w.error or 'state not reached'})"
    return f"{1e3 * w.stroke:.4f} mm, {where}"


def summary(result: BiasDesign) -> list[str]:
    """Markdown lines describing the design and the comparison (see the module text)."""
    s = result.settings
    units = ", ".join(str(k + 1) for k in s.units)
    aware, single = result.aware.verification, result.single.verification
    nominal = result.single_nominal
    lines = ["# Bias design", "",
             f"- family `{s.family}`, V = {s.voltage:g} V, units {units}"
             f"{' (one shared design)' if s.shared else ' (one design per unit)'}",
             f"- scenarios `{s.scenarios}`: {len(result.scenarios)} (unit states listed as `s` stroking, `V` at "
             "V, `0` at 0 V)",
             f"- stability margin K = {s.margin:.4g} N/m, max bias force "
             f"{'none' if math.isinf(s.max_force) else f'{s.max_force:.4g} N'}, position range "
             f"[{1e3 * s.position_range[0]:.3f}, {1e3 * s.position_range[1]:.3f}] mm, "
             f"snap-through {'allowed' if s.allow_snap else 'not allowed'}",
             f"- membrane scales: softest nominal slope {result.stiffness_scale:.4g} N/m, largest 0 V force "
             f"{result.force_scale:.4g} N", "",
             "## Designs", "", "| unit | single-unit-tuned | array-aware |", "|---|---|---|"]
    for k, a, b in zip(s.units, result.single.laws, result.aware.laws):
        lines.append(f"| {k + 1} | {_law_text(a)} | {_law_text(b)} |")
    lines += ["", "## Strokes (full biased solves)", "",
              "| design | where | smallest stroke [mm] | worst case | all stable | snaps |",
              "|---|---|---|---|---|---|",
              f"| single-unit-tuned | each unit alone (neighbours free, 0 V) | {1e3 * nominal.min_stroke:.4f} | "
              f"{_worst(nominal)} | {nominal.all_stable} | {nominal.any_snap} |",
              f"| single-unit-tuned | the array, every scenario | {1e3 * single.min_stroke:.4f} | "
              f"{_worst(single)} | {single.all_stable} | {single.any_snap} |",
              f"| array-aware | the array, every scenario | {1e3 * aware.min_stroke:.4f} | {_worst(aware)} | "
              f"{aware.all_stable} | {aware.any_snap} |", ""]
    lo, hi = s.position_range
    for name, v in (("single-unit-tuned", single), ("array-aware", aware)):
        heights = [st.position[r.scenario.unit] for r in v.rows for st in (r.low, r.high) if st is not None]
        inside = bool(heights) and lo <= min(heights) and max(heights) <= hi
        lines.append(f"- {name} in the array: heights {1e3 * min(heights, default=math.nan):.3f} to "
                     f"{1e3 * max(heights, default=math.nan):.3f} mm ({'inside' if inside else 'OUTSIDE'} the "
                     f"position range), smallest margin {v.min_margin:.4g} N/m "
                     f"({'>=' if v.min_margin >= s.margin else 'BELOW'} K).")
    lines.append("")
    if math.isfinite(nominal.min_stroke) and nominal.min_stroke > 0:
        lost = 1.0 - single.min_stroke / nominal.min_stroke if math.isfinite(single.min_stroke) else 1.0
        lines.append(f"The single-unit-tuned design loses {100 * lost:.1f} % of its nominal stroke in the array's "
                     "worst case.")
    if math.isfinite(single.min_stroke) and single.min_stroke > 0 and math.isfinite(aware.min_stroke):
        lines.append(f"The array-aware design's worst case is {100 * (aware.min_stroke / single.min_stroke - 1):+.1f} %"
                     " against the single-unit-tuned design's in the array.")
    lines += ["", "## Inner model against full solves", "",
              "| pass | largest stroke difference / smallest stroke | feasible on the inner model | designs evaluated "
              "| sweeps [s] | optimisation [s] | verification [s] |", "|---|---|---|---|---|---|---|"]
    for i, it in enumerate(result.iterations, start=1):
        sec = it.seconds
        lines.append(f"| {i} | {100 * it.agreement:.3f} % | {it.inner_feasible} | {it.evaluations} | "
                     f"{sec['sweeps']:.1f} | {sec['optimisation']:.1f} | {sec['verification']:.1f} |")
    lines += ["", f"{'Converged' if result.converged else 'NOT converged'} (tolerance {100 * s.tolerance:g} %); "
              f"aware design: smallest stability margin {aware.min_margin:.4g} N/m, largest bias force "
              f"{aware.max_bias_force:.4g} N; total {result.seconds:.0f} s."]
    if aware.any_hysteresis:
        lines.append("Warning: some stroke of the array-aware design does not return to its low state.")
    if not result.margin_kept:
        lines.append(f"Warning: the full solves of the array-aware design go below the margin K at a path point "
                     f"({aware.min_margin:.4g} < {s.margin:.4g} N/m) where the inner model kept it: see "
                     "`margin_N_per_m` in the strokes CSV.")
    if aware.any_snap and not s.allow_snap:
        lines.append("Warning: the full solves of the array-aware design snap through where the inner model saw no "
                     "snap (not allowed without --allow-snap): see `snapped` in the strokes CSV.")
    return lines


"""The twin's numbers behind docs/paper.md, the comparison with the paper's sections 3-7.

Run from the repository root:

    .venv/bin/python tools/paper_numbers.py --workers 2            # default mesh, 15 steps: print the tables
    .venv/bin/python tools/paper_numbers.py --workers 2 --write    # ... and rewrite docs/paper.md's generated blocks
    .venv/bin/python tools/paper_numbers.py --mesh coarse --steps 3 --check   # what test/test_paper_docs.py does

Every number in docs/paper.md's generated blocks comes from :func:`compute`: it builds
all the curves (the section-5 curves of figures 12-16, the section-6 indices and
sweeps, the interpretation alternatives and a mesh study), runs them in one batch on
``--workers`` processes, and evaluates named values.  :data:`ROWS` turn the values into
the comparison table, each with its verdict rule; :data:`CHOICES` into the table of
interpretation choices.  ``--check`` recomputes the values and compares them with the
numbers block of docs/paper.md within :func:`tolerance`.  Not a test; not a benchmark.
"""

from __future__ import annotations

import argparse
import json
import math
import re
import sys
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import numpy as np

from dea_array_twin import ArrayConfig, ArrayTwin
from dea_array_twin.model.geometry import edge_distance
from dea_array_twin.parallel import run_tasks
from dea_array_twin.studies import tasks as study
from dea_array_twin.studies.tasks import SWEEPS, CurveResult, CurveTask

DOC = Path(__file__).resolve().parents[1] / "docs" / "paper.md"
#: The test meshes: the default (Table 1 config) and the coarse one of test/conftest.py.
MESHES = {"default": {}, "coarse": {"mesh_size": 20e-3, "mesh_size_indenter": 2.5e-3, "mesh_size_electrode": 5e-3}}
#: Mesh study (section 4.2.2): element sizes (far field, indenter, electrode) [m] of three meshes.
MESH_STUDY = {"coarse": (20e-3, 2.5e-3, 5e-3), "default": (10e-3, 1.25e-3, 2.5e-3),
              "fine": (5e-3, 0.625e-3, 1.25e-3)}
#: Section-6 values: the paper's spacings (the nominal 15 mm included); every other edge distance and
#: pre-stretch of its ranges, and the down-scalings the statements need (the test's time budget).
#: ``dea-twin study sweep all`` gives the full ranges.
SWEEP_VALUES = {"spacing": SWEEPS["spacing"].values, "edge_distance": (0.010, 0.020, 0.030, 0.040, 0.050),
                "prestretch": (1.10, 1.25, 1.40, 1.55, 1.70, 1.80), "scale": (1.0, 13.0, 14.0, 100.0)}
#: Spacings [m] of the two frame-length alternatives of the spacing sweep.
SPACING_ALTERNATIVES = (0.001, 0.006, 0.011, 0.015)
#: Edge distances [m] of the "b on all four sides" alternative.
ALL_SIDES = (0.010, 0.030, 0.050)
#: An assumed slip table for the eq. 11 check (the paper's figure 14 gives no numbers in the text).
GAMMA = ((0.0, 0.0075, 0.015), (1.0, 0.96, 0.90))


# ------------------------------------------------------------------- the curves

def _mesh(cfg: ArrayConfig, sizes: tuple[float, float, float]) -> ArrayConfig:
    return cfg.replace(mesh_size=sizes[0], mesh_size_indenter=sizes[1], mesh_size_electrode=sizes[2])


def _row_length(base: ArrayConfig, spacing: float, margin: float) -> ArrayConfig:
    """The spacing sweep's alternatives: L follows d, the short edges ``margin`` from the electrodes."""
    return base.replace(spacing=spacing, length=base.cols * base.electrode_diameter + (base.cols - 1) * spacing
                        + 2 * margin)


def _all_sides(base: ArrayConfig, b: float) -> ArrayConfig:
    """The edge sweep's alternative: every electrode-to-frame distance is b (L and H follow)."""
    cfg = SWEEPS["edge_distance"].apply(base, b)
    return cfg.replace(length=base.cols * base.electrode_diameter + (base.cols - 1) * base.spacing + 2 * b)


def plan(base: ArrayConfig, steps: int) -> list[CurveTask]:
    """Every curve the numbers need, keyed ``(group, ...)``."""
    tasks = []
    for name, values in SWEEP_VALUES.items():
        tasks += study.sweep_tasks(SWEEPS[name], base, values, steps)
    tasks += study.shape_tasks(base, steps)
    d = base.electrode_diameter
    for spacing in (0.001, base.spacing):  # "not deflected" read as held at 0 m
        tasks += study.coupling_tasks(base.replace(spacing=spacing), steps, ("held", spacing), undeflected=0.0)
    short = 0.5 * (base.length - base.cols * base.electrode_diameter - (base.cols - 1) * base.spacing)
    for spacing in SPACING_ALTERNATIVES:
        if spacing != base.spacing:  # the same array as the sweep's
            tasks += study.coupling_tasks(_row_length(base, spacing, short), steps, ("short_edges_fixed", spacing))
        tasks += study.coupling_tasks(_row_length(base, spacing, edge_distance(base)), steps, ("b_all_sides", spacing))
    for b in ALL_SIDES:
        tasks += study.coupling_tasks(_all_sides(base, b), steps, ("all_sides", b))
    exp = base.experimental_hv()
    tasks += [t for t in study.coupling_tasks(base, steps, ("hv_experimental",), hv=exp) if t.voltage > 0]
    for lp in base.experimental_hv_prestretch:
        cfg = base.replace(prestretch=lp)
        tasks += study.curves_tasks(cfg, steps)
        tasks += study.curves_tasks(cfg, steps, neighbours=[0.0])
    for mesh, sizes in MESH_STUDY.items():  # fixed meshes, fixed points (0, 5, 10, 15 mm)
        tasks.append(CurveTask(_mesh(base, sizes), 1, None, 0.0, 0.75 * d, 3, ("mesh", mesh)))
    slip = base.replace(slip_displacement=GAMMA[0], slip_factor=GAMMA[1])
    tasks.append(CurveTask(slip, 1, None, 0.0, 0.75 * d, steps, ("gamma",)))
    return tasks


def _field(res: CurveResult, kind: str) -> float:
    """DE2's field at the end of the stroke [V/m]: from its capacitance (:func:`_mean_field`), or its peak."""
    return _mean_field(res) if kind == "mean" else float(res.peak_field[-1, 1])


def _field_tasks(results: dict, base: ArrayConfig, steps: int, round_: int) -> list[CurveTask]:
    """DE2 (neighbours free) at the next guess of the voltage that gives 80 V/um at 15 mm.

    The field is nearly proportional to V: the first guess scales the experiments' HV
    by 80 V/um over its field, later ones are secant steps on the last two voltages.
    """
    tasks = []
    for lp in base.experimental_hv_prestretch:
        cfg = base.replace(prestretch=lp)
        first = results[("curves", lp, f"unit 2, neighbours free, {cfg.experimental_hv():g} V")]
        for kind in ("mean", "peak"):
            tried = [first] + [results[("field", lp, kind, r)] for r in range(round_)]
            points = [(r.task.voltage, _field(r, kind)) for r in tried]
            v1, e1 = points[-1]
            volt = v1 * study.CRITICAL_FIELD / e1
            if len(points) > 1:
                v0, e0 = points[-2]
                volt = v1 + (study.CRITICAL_FIELD - e1) * (v1 - v0) / (e1 - e0)
            tasks.append(CurveTask(cfg, 1, None, float(round(volt)), first.task.stroke, steps,
                                   ("field", lp, kind, round_)))
    return tasks


#: Rounds of :func:`_field_tasks`: a scaling and two secant steps.
FIELD_ROUNDS = 3


def _mean_field(res: CurveResult, unit: int = 1) -> float:
    """Field from the electrode's capacitance at the last point: ``V/t0 sqrt(C t0 / (eps A0))`` [V/m].

    With eq. 7, ``C = eps/t0 int det C dA0``, so ``C t0 / (eps A0)`` is the mean of
    ``det C = (l1 l2)^2`` over the electrode: this is the true field ``V/(t0 l3) =
    V l1 l2 / t0`` at the r.m.s. area stretch of the electrode.
    """
    cfg = res.task.config
    area = math.pi * (0.5 * cfg.scaled("electrode_diameter")) ** 2
    mean_det = res.capacitance[-1, unit] * cfg.thickness / (cfg.permittivity * area)
    return res.task.voltage / cfg.thickness * math.sqrt(mean_det)


# ------------------------------------------------------------------- the values

def _index_values(prefix: str, rows: list[dict], label: Callable[[float], str]) -> dict[str, float]:
    out = {}
    for row in rows:
        for key in ("eta_f_lv", "eta_f_hv", "eta_c"):
            out[f"{prefix}.{label(row['value'])}.{key}"] = row[key]
    return out


def _mm(v: float) -> str:
    return f"{v * 1e3:g}mm"


def evaluate(results: dict, base: ArrayConfig) -> dict[str, float]:
    """The named values of docs/paper.md from the solved curves (keyed by task key)."""
    by_group: dict[str, list] = {}
    for key, res in results.items():
        by_group.setdefault(key[0], []).append(res)
    v: dict[str, float] = {}
    nominal = [r for r in by_group["spacing"] if r.task.key[1] == base.spacing]
    base_row = study.index_rows(nominal)[0]
    v.update({f"base.{k}": base_row[k] for k in ("eta_f_lv", "eta_f_hv", "eta_c", "hv_voltage_V")})
    labels = {"spacing": _mm, "edge_distance": _mm, "prestretch": lambda x: f"{x:.2f}", "scale": lambda x: f"{x:g}"}
    for name, label in labels.items():
        rows = study.index_rows(by_group[name])
        v.update(_index_values(name, rows, label))
        if name == "scale":
            v["scale.air_gap_mm"] = rows[0]["air_gap_min_m"] * 1e3
            v["scale.limit_k"] = rows[0]["d_m"] / rows[0]["air_gap_min_m"]
    shape = {r.task.key[1:]: r for r in by_group["shape"]}
    for case in ("lv", "hv"):
        df, dc = study.shape_difference(shape[("circle", case)], shape[("square", case)])
        v[f"shape.{case}.force_pct"], v[f"shape.{case}.dc_pct"] = 100 * df, 100 * dc
    for group in ("held", "short_edges_fixed", "b_all_sides", "all_sides"):
        v.update(_index_values(group, study.index_rows(by_group[group]), _mm))
    hv = {r.task.key[1]: r for r in by_group["hv_experimental"]}
    centre = 1
    f_def, f_pert = (float(hv[c].force[:, centre].max()) for c in ("hv_default", "hv_perturbed"))
    v["hv_experimental.eta_f_hv"] = 100 * (f_def - f_pert) / f_def
    v["hv_experimental.wrinkled"] = float(any(hv[c].wrinkled.any() for c in hv))
    v["base.hv_wrinkled"] = float(any(r.wrinkled.any() for r in nominal if r.task.voltage > 0))
    v["base.hv_field_exceeded"] = float(any(r.field_exceeded.any() for r in nominal if r.task.voltage > 0))
    v.update(_section5_values(by_group["curves"], base))
    v.update(_mesh_values({r.task.key[1]: r for r in by_group["mesh"]}))
    plain = results[("curves", base.prestretch, f"unit 2, neighbours free, {0:g} V")]
    slipped = by_group["gamma"][0]
    v["gamma.force_pct"] = 100 * (slipped.force[-1, 1] / plain.force[-1, 1] - 1)
    v["gamma.dc_pct"] = 100 * (slipped.delta_capacitance[-1, 1] / plain.delta_capacitance[-1, 1] - 1)
    for res in by_group["field"]:
        lp, kind, round_ = res.task.key[1:]
        if round_ == FIELD_ROUNDS - 1:
            v[f"field.{lp:.2f}.{kind}.voltage_V"] = res.task.voltage
            v[f"field.{lp:.2f}.{kind}.field_V_um"] = _field(res, kind) / 1e6
    return v


def _section5_values(curves: list[CurveResult], base: ArrayConfig) -> dict[str, float]:
    """Figures 12-16: dC at 15 mm (self and cross), force maxima per pre-load, start offsets, fields."""
    v: dict[str, float] = {}
    largest = -math.inf
    for lp in base.experimental_hv_prestretch:
        hv = base.replace(prestretch=lp).experimental_hv()
        mine = {(r.task.swept, None if r.task.neighbours is None else round(r.task.neighbours, 9), r.task.voltage): r
                for r in curves if r.task.key[1] == lp}
        tag = f"{lp:.2f}"
        for k in (0, 1):
            free_lv = mine[(k, None, 0.0)]
            for m in (0, 1):
                v[f"curves.{tag}.dc.DE{k + 1}_deformed.DE{m + 1}_pF"] = free_lv.delta_capacitance[-1, m] * 1e12
            for nb in (None, 0.0, 0.004, 0.006, 0.008):
                for volt, name in ((0.0, "lv"), (hv, "hv")):
                    label = "free" if nb is None else _mm(nb)
                    v[f"curves.{tag}.fmax.DE{k + 1}.{label}.{name}_N"] = float(mine[(k, nb, volt)].force[:, k].max())
        flat = mine[(1, None, 0.0)].capacitance[0, 1]
        v[f"curves.{tag}.start_offset.hv_pF"] = (mine[(1, None, hv)].capacitance[0, 1] - flat) * 1e12
        v[f"curves.{tag}.start_offset.8mm_pF"] = (mine[(1, 0.008, 0.0)].capacitance[0, 1] - flat) * 1e12
        end = mine[(1, None, hv)]
        v[f"curves.{tag}.field15.mean_V_um"] = _mean_field(end) / 1e6
        v[f"curves.{tag}.field15.peak_V_um"] = end.peak_field[-1, 1] / 1e6
        v[f"curves.{tag}.hv_V"] = hv
        steps = [np.diff([v[f"curves.{tag}.fmax.DE{k}.{nb}.{name}_N"] for nb in ("free", "4mm", "6mm", "8mm")])
                 for k in (1, 2) for name in ("lv", "hv")]
        largest = max(largest, float(np.max(steps)))
        v[f"curves.{tag}.flagged"] = float(any(r.wrinkled.any() or r.field_exceeded.any() for r in mine.values()))
        v[f"curves.{tag}.dc.DE1_over_DE2_pct"] = 100 * (v[f"curves.{tag}.dc.DE1_deformed.DE1_pF"]
                                                      / v[f"curves.{tag}.dc.DE2_deformed.DE2_pF"] - 1)
    v["curves.fmax.largest_step_N"] = largest
    return v


def _mesh_values(curves: dict[str, CurveResult]) -> dict[str, float]:
    """Section 4.2.2's measure: mean relative force error of the central unit's curve between meshes [%]."""
    v = {f"mesh.{name}.elements": float(ArrayTwin(res.task.config).model.mesh.n_elements)
         for name, res in curves.items()}

    def err(a: str, b: str, field: str = "force") -> float:
        x, y = getattr(curves[a], field)[1:, 1], getattr(curves[b], field)[1:, 1]
        return float(100 * np.mean(np.abs(x - y) / np.abs(y)))

    for field, unit in (("force", "force"), ("capacitance", "cap"), ("delta_capacitance", "dc")):
        a, b = getattr(curves["coarse"], field)[-1, 1], getattr(curves["default"], field)[-1, 1]
        v[f"mesh.coarse_vs_default.{unit}15_pct"] = float(100 * abs(a - b) / abs(b))
    v["mesh.coarse_vs_default.force_pct"] = err("coarse", "default")
    v["mesh.default_vs_fine.force_pct"] = err("default", "fine")
    v["mesh.coarse_vs_default.dc_pct"] = err("coarse", "default", "delta_capacitance")
    v["mesh.default_vs_fine.dc_pct"] = err("default", "fine", "delta_capacitance")
    return v


def compute(base: ArrayConfig, steps: int, workers: int = 1, log=print) -> dict[str, float]:
    """Every named value of docs/paper.md for ``base`` (the mesh) and ``steps`` per curve."""
    tic = time.perf_counter()
    tasks = plan(base, steps)
    log(f"paper_numbers: {len(tasks)} curves on {workers} worker(s)...")
    results = {t.key: r for t, r in zip(tasks, run_tasks(study.run_curve, tasks, workers=workers))}
    for round_ in range(FIELD_ROUNDS):
        more = _field_tasks(results, base, steps, round_)
        results.update({t.key: r for t, r in zip(more, run_tasks(study.run_curve, more, workers=workers))})
    log(f"paper_numbers: {len(results)} curves in {time.perf_counter() - tic:.0f} s")
    return evaluate(results, base)


# ------------------------------------------------------------------- tolerances

def tolerance(key: str) -> float:
    """How far a value on the coarse mesh (3 steps) may be from the docs' (default mesh, 15 steps).

    Absolute, in the value's unit: coupling indices and percentages 0.3 points; forces
    0.5 % of the value; capacitance changes 0.5 % (0.3 % observed: dC is a difference of
    two capacitances); fields and voltages 1.5 % (the peak field sits at the indenter
    edge, where the coarse mesh is coarsest: 3 % there); mesh-study values are computed on
    fixed meshes and points, so only the solver's tolerance moves them: 0.001 points
    (element counts are integers); flags exactly.
    """
    if key.startswith("mesh."):
        return 1e-3
    if ".peak" in key:
        return 3e-2
    if key.endswith(("_N", "_pF")):
        return 5e-3
    if key.endswith(("_V", "_V_um", "limit_k", "air_gap_mm")):
        return 1.5e-2
    if key.endswith(("wrinkled", "exceeded", "flagged")):
        return 0.0
    return 0.3


def relative(key: str) -> bool:
    """Whether :func:`tolerance` is relative to the value (forces, capacitances, fields, voltages)."""
    return not key.startswith("mesh.") and key.endswith(("_N", "_pF", "_V", "_V_um", "limit_k", "air_gap_mm"))


def mismatches(docs: dict[str, float], fresh: dict[str, float]) -> list[str]:
    """The keys where ``fresh`` is off ``docs`` by more than the tolerance (or missing), as messages."""
    out = [f"{k}: missing from the recomputed values" for k in docs if k not in fresh]
    out += [f"{k}: not in the docs" for k in fresh if k not in docs]
    for key in sorted(set(docs) & set(fresh)):
        tol = tolerance(key) * (abs(docs[key]) if relative(key) else 1.0)
        if not abs(fresh[key] - docs[key]) <= tol:
            out.append(f"{key}: docs {docs[key]:.6g}, recomputed {fresh[key]:.6g} (tolerance {tol:.3g})")
    return out


# ------------------------------------------------------------------- the tables

INDICES = ("eta_f_lv", "eta_f_hv", "eta_c")
REPRODUCED, NOT, RIG, UNCHECKED = ("reproduced", "not reproduced", "not reproducible without rig data",
                                   "not checked here")


def near(value: float, target: float, within: float = 1.0) -> str:
    """The verdict on a "~target" read off a figure: reproduced when within ``within`` points."""
    return REPRODUCED if abs(value - target) <= within else NOT


def when(ok: bool) -> str:
    return REPRODUCED if ok else NOT


@dataclass(frozen=True)
class Row:
    """One statement of the paper, the twin's numbers, the command behind them and the verdict."""

    section: str
    paper: str
    twin: Callable[[dict], str]
    command: str
    verdict: Callable[[dict], str]
    rule: str = ""


def _idx(v: dict, prefix: str, values: tuple, key: str, fmt: Callable = _mm) -> np.ndarray:
    return np.array([v[f"{prefix}.{fmt(x)}.{key}"] for x in values])


def _lp(x: float) -> str:
    return f"{x:.2f}"


SP, ED, PS = SWEEP_VALUES["spacing"], SWEEP_VALUES["edge_distance"], SWEEP_VALUES["prestretch"]
CURVES = "`dea-twin study curves` (summary.md)"
SWEEP = "`dea-twin study sweep {}` (sweep_{}.csv)"
SCRIPT = "`tools/paper_numbers.py`"


def _rows() -> list[Row]:
    f = "curves.1.10.fmax.DE2"
    rows = [
        Row("3.2, fig. 6", "Pre-deflected neighbours change the central DE's force curves (lower force)",
            lambda v: (f"DE2 at 15 mm, lp 1.10: {v[f + '.free.lv_N']:.3f} N with free neighbours, "
                       f"{v[f + '.8mm.lv_N']:.3f} N with them at 8 mm "
                       f"({100 * (v[f + '.8mm.lv_N'] / v[f + '.free.lv_N'] - 1):+.1f} %); "
                       f"at 2730 V {v[f + '.free.hv_N']:.3f} -> {v[f + '.8mm.hv_N']:.3f} N"),
            CURVES, lambda v: when(v[f + ".8mm.lv_N"] < v[f + ".free.lv_N"]
                                   and v[f + ".8mm.hv_N"] < v[f + ".free.hv_N"])),
        Row("3.2, fig. 6", "A negative-rate bias matched to the nominal curves loses much of its stroke when the "
            "neighbours deflect", lambda v: "needs units on bias elements (actuator mode); not computed here",
            "-", lambda v: UNCHECKED),
        Row("4.2.1, fig. 9", "The membrane model is within 1 % of a full 3D model (one DE, lp 1.10, 0 and 2730 V)",
            lambda v: "no 3D model here; the membrane FE is within 0.1 % of an independent axisymmetric "
                      "solution of the same equations (`test_cone_dea_matches_axisymmetric_solution`)",
            "-", lambda v: UNCHECKED),
        Row("4.2.2, fig. 10", "Mesh study: even the coarsest mesh (214 elements) is within about 1 % of the next "
            "finer one; the error falls with refinement",
            lambda v: (f"mean relative error of DE2's force at 5/10/15 mm (neighbours free, 0 V): "
                       f"{v['mesh.coarse_vs_default.force_pct']:.3f} % between the coarse "
                       f"({v['mesh.coarse.elements']:.0f} elements) and the default mesh "
                       f"({v['mesh.default.elements']:.0f}), {v['mesh.default_vs_fine.force_pct']:.3f} % between the "
                       f"default and a fine one ({v['mesh.fine.elements']:.0f}); dC: "
                       f"{v['mesh.coarse_vs_default.dc_pct']:.3f} % and {v['mesh.default_vs_fine.dc_pct']:.3f} %"),
            SCRIPT, lambda v: when(v["mesh.coarse_vs_default.force_pct"] <= 1.0
                                   and v["mesh.default_vs_fine.force_pct"] < v["mesh.coarse_vs_default.force_pct"]),
            "rule: coarse within 1 %, error falling"),
    ]
    for lp, hv in (("1.10", 2730), ("1.20", 2300)):
        rows.append(Row(
            "5.1", f"{hv} V at lp {lp} gives a safe 80 V/um when DE2 reaches 15 mm",
            lambda v, lp=lp, hv=hv: (
                f"field at 15 mm, {hv} V: {v[f'curves.{lp}.field15.mean_V_um']:.1f} V/um from the electrode's "
                f"capacitance (r.m.s. area stretch), {v[f'curves.{lp}.field15.peak_V_um']:.1f} V/um at its peak "
                "(indenter edge); "
                f"80 V/um needs {v[f'field.{lp}.mean.voltage_V']:.0f} V (mean: "
                f"{v[f'field.{lp}.mean.field_V_um']:.1f} V/um) or {v[f'field.{lp}.peak.voltage_V']:.0f} V (peak: "
                f"{v[f'field.{lp}.peak.field_V_um']:.1f} V/um)"),
            SCRIPT + f"; `peak_field2_V_m` in force_lp{lp}.csv",
            lambda v, lp=lp: when(abs(v[f"curves.{lp}.field15.mean_V_um"] - 80) <= 2
                                  or abs(v[f"curves.{lp}.field15.peak_V_um"] - 80) <= 2),
            "rule: either field within 2 V/um of 80"))
    rows += [
        Row("5.2, table 1", "Yeoh c10, c20, c30 identified by Nelder-Mead from the lp 1.10 curves with neighbours at "
            "4 and 6 mm", lambda v: "the twin uses Table 1's values; `dea-twin calibrate` runs the same fit on "
            "measured curves (shown on synthetic data in docs/calibration.md)", "`dea-twin calibrate`",
            lambda v: RIG),
        Row("5.2, figs. 12-13", "DE1's own capacitance change is larger than DE2's, at both pre-stretches",
            lambda v: "; ".join(
                f"lp {lp}: {v[f'curves.{lp}.dc.DE1_deformed.DE1_pF']:.2f} vs "
                f"{v[f'curves.{lp}.dc.DE2_deformed.DE2_pF']:.2f} pF at 15 mm "
                f"({v[f'curves.{lp}.dc.DE1_over_DE2_pct']:+.2f} %)" for lp in ("1.10", "1.20")),
            CURVES, lambda v: when(all(v[f"curves.{lp}.dc.DE1_over_DE2_pct"] > 0 for lp in ("1.10", "1.20")))),
        Row("5.2, figs. 12-13", "The higher the pre-stretch, the larger the capacitance change (eq. 7)",
            lambda v: (f"DE2 at 15 mm: {v['curves.1.10.dc.DE2_deformed.DE2_pF']:.1f} pF at lp 1.10, "
                       f"{v['curves.1.20.dc.DE2_deformed.DE2_pF']:.1f} pF at lp 1.20"),
            CURVES, lambda v: when(v["curves.1.20.dc.DE2_deformed.DE2_pF"] > v["curves.1.10.dc.DE2_deformed.DE2_pF"])),
        Row("5.2, figs. 12-13", "Deflecting DE1 changes DE2's capacitance by a small, yet measurable amount",
            lambda v: "; ".join(
                f"lp {lp}: {v[f'curves.{lp}.dc.DE1_deformed.DE2_pF']:.2f} pF, "
                f"{100 * v[f'curves.{lp}.dc.DE1_deformed.DE2_pF'] / v[f'curves.{lp}.dc.DE2_deformed.DE2_pF']:.1f} % "
                "of DE2's own" for lp in ("1.10", "1.20")),
            CURVES, lambda v: when(all(0 < v[f"curves.{lp}.dc.DE1_deformed.DE2_pF"]
                                       < 0.2 * v[f"curves.{lp}.dc.DE2_deformed.DE2_pF"] for lp in ("1.10", "1.20"))),
            "rule: above 0 and below 20 % of DE2's own"),
        Row("5.2, figs. 12-14, table 2", "Capacitance FIT 84.05-99.31 % per curve, average > 92 %, with the slip "
            "correction gamma(d) of eq. 11 fitted to the lp 1.10 cross curves (figure 14)",
            lambda v: "needs the measured curves; `dea-twin calibrate --slip` fits gamma the same way "
                      "(synthetic example in docs/calibration.md)", "`dea-twin calibrate --slip`", lambda v: RIG),
        Row("5.2", "The slip correction barely changes the force curves",
            lambda v: (f"with an assumed gamma = 1, 0.96, 0.90 at 0, 7.5, 15 mm (figure 14's values are not in "
                       f"the text): DE2's force at 15 mm {v['gamma.force_pct']:+.2f} %, its dC "
                       f"{v['gamma.dc_pct']:+.2f} %"),
            SCRIPT, lambda v: when(abs(v["gamma.force_pct"]) < min(2.0, abs(v["gamma.dc_pct"]) / 3)),
            "rule: force change below 2 % and below a third of the dC change"),
        Row("5.2, figs. 15-16", "The force falls a little as the neighbours' pre-deflection grows (0, 4, 6, 8 mm)",
            lambda v: ("DE2, lp 1.10, 0 V: " + ", ".join(f"{v[f + '.' + nb + '.lv_N']:.3f}"
                                                         for nb in ("free", "4mm", "6mm", "8mm"))
                       + " N; largest change from one pre-load to the next, over DE1 and DE2, 0 V and HV, lp 1.10 "
                       f"and 1.20: {1e3 * v['curves.fmax.largest_step_N']:+.1f} mN"),
            CURVES, lambda v: when(v["curves.fmax.largest_step_N"] < 0)),
        Row("5.2, figs. 15-16, table 3", "Force FIT 86.21-98.04 % per curve, average > 93 % (abstract, section 7: "
            "93 % force, 92 % capacitance)", lambda v: "needs the measured curves", "`dea-twin calibrate`",
            lambda v: RIG),
        Row("6.2, fig. 19", "Force coupling ~12 % at d = 1 mm: eta_F,LV",
            lambda v: f"{v['spacing.1mm.eta_f_lv']:.1f} %", SWEEP.format("spacing", "spacing"),
            lambda v: near(v["spacing.1mm.eta_f_lv"], 12)),
        Row("6.2, fig. 19", "Force coupling ~12 % at d = 1 mm: eta_F,HV",
            lambda v: f"{v['spacing.1mm.eta_f_hv']:.1f} %", SWEEP.format("spacing", "spacing"),
            lambda v: near(v["spacing.1mm.eta_f_hv"], 12)),
        Row("6.2, fig. 19", "Force coupling falls to ~1 % at d = 15 mm",
            lambda v: f"eta_F,LV {v['spacing.15mm.eta_f_lv']:.1f} %, eta_F,HV {v['spacing.15mm.eta_f_hv']:.1f} %",
            SWEEP.format("spacing", "spacing"),
            lambda v: when(near(v["spacing.15mm.eta_f_lv"], 1) == near(v["spacing.15mm.eta_f_hv"], 1) == REPRODUCED)),
        Row("6.2, fig. 19", "Force coupling falls as d grows, HV always slightly above LV",
            lambda v: (f"both fall at every step of d = 1-15 mm; HV - LV between "
                       f"{np.min(_idx(v, 'spacing', SP, 'eta_f_hv') - _idx(v, 'spacing', SP, 'eta_f_lv')):.1f} and "
                       f"{np.max(_idx(v, 'spacing', SP, 'eta_f_hv') - _idx(v, 'spacing', SP, 'eta_f_lv')):.1f} "
                       "points") if all(np.all(np.diff(_idx(v, 'spacing', SP, k)) < 0) for k in ("eta_f_lv",
                                                                                                 "eta_f_hv"))
            else "the force indices do not fall at every step", SWEEP.format("spacing", "spacing"),
            lambda v: when(all(np.all(np.diff(_idx(v, "spacing", SP, k)) < 0) for k in ("eta_f_lv", "eta_f_hv"))
                           and np.all(_idx(v, "spacing", SP, "eta_f_hv") > _idx(v, "spacing", SP, "eta_f_lv")))),
        Row("6.2, fig. 19", "Capacitance coupling ~15 % at d = 1 mm",
            lambda v: f"eta_C {v['spacing.1mm.eta_c']:.1f} %", SWEEP.format("spacing", "spacing"),
            lambda v: near(v["spacing.1mm.eta_c"], 15)),
        Row("6.2, fig. 19; 7", "Capacitance coupling converges to a plateau near 8 % as d grows",
            lambda v: ("eta_C at d = " + ", ".join(f"{x * 1e3:g}" for x in SP) + " mm: "
                       + ", ".join(f"{y:.1f}" for y in _idx(v, "spacing", SP, "eta_c"))
                       + " %: still falling by "
                       f"{-np.diff(_idx(v, 'spacing', SP, 'eta_c'))[-2:].sum():.1f} points over the last 4.5 mm"),
            SWEEP.format("spacing", "spacing"),
            lambda v: when(abs(np.diff(_idx(v, "spacing", SP, "eta_c"))[-2:].sum()) <= 0.5
                           and near(v["spacing.15mm.eta_c"], 8) == REPRODUCED)),
        Row("6.2, fig. 20; 7", "Force coupling rises with the edge distance b, more for HV",
            lambda v: (f"b = 10 -> 50 mm: eta_F,LV {v['edge_distance.10mm.eta_f_lv']:.1f} -> "
                       f"{v['edge_distance.50mm.eta_f_lv']:.1f} %, eta_F,HV {v['edge_distance.10mm.eta_f_hv']:.1f} -> "
                       f"{v['edge_distance.50mm.eta_f_hv']:.1f} %, both rising at every step"
                       if all(np.all(np.diff(_idx(v, "edge_distance", ED, k)) > 0) for k in ("eta_f_lv", "eta_f_hv"))
                       else "the force indices do not rise at every step"),
            SWEEP.format("edge_distance", "edge_distance"),
            lambda v: when(all(np.all(np.diff(_idx(v, "edge_distance", ED, k)) > 0) for k in ("eta_f_lv", "eta_f_hv"))
                           and np.ptp(_idx(v, "edge_distance", ED, "eta_f_hv"))
                           > np.ptp(_idx(v, "edge_distance", ED, "eta_f_lv")))),
        Row("6.2, fig. 20; 7", "Capacitance coupling falls from ~10 % to almost 0 % as b grows from 10 to 50 mm",
            lambda v: ("eta_C at b = " + ", ".join(f"{x * 1e3:g}" for x in ED) + " mm: "
                       + ", ".join(f"{y:.1f}" for y in _idx(v, "edge_distance", ED, "eta_c")) + " %"),
            SWEEP.format("edge_distance", "edge_distance"),
            lambda v: when(near(v["edge_distance.10mm.eta_c"], 10) == near(v["edge_distance.50mm.eta_c"], 0)
                           == REPRODUCED)),
        Row("6.2, fig. 21; 7", "Pre-stretch lowers the capacitance coupling",
            lambda v: (f"eta_C {v['prestretch.1.10.eta_c']:.1f} % at lp 1.10, {v['prestretch.1.80.eta_c']:.1f} % at "
                       f"1.80, falling at every step" if np.all(np.diff(_idx(v, "prestretch", PS, "eta_c", _lp)) < 0)
                       else "eta_C does not fall at every step"),
            SWEEP.format("prestretch", "prestretch"),
            lambda v: when(np.all(np.diff(_idx(v, "prestretch", PS, "eta_c", _lp)) < 0))),
        Row("6.2, fig. 21", "... to approximately 2 %",
            lambda v: f"{v['prestretch.1.80.eta_c']:.1f} % at lp 1.80", SWEEP.format("prestretch", "prestretch"),
            lambda v: near(v["prestretch.1.80.eta_c"], 2)),
        Row("6.2, fig. 21; 7", "Force coupling stays at about 8 % for pre-stretches above 25 %",
            lambda v: (f"lp 1.25-1.80: eta_F,LV {np.min(_idx(v, 'prestretch', PS[3:], 'eta_f_lv', _lp)):.1f}-"
                       f"{np.max(_idx(v, 'prestretch', PS[3:], 'eta_f_lv', _lp)):.1f} %, eta_F,HV "
                       f"{np.min(_idx(v, 'prestretch', PS[3:], 'eta_f_hv', _lp)):.1f}-"
                       f"{np.max(_idx(v, 'prestretch', PS[3:], 'eta_f_hv', _lp)):.1f} %"),
            SWEEP.format("prestretch", "prestretch"),
            lambda v: when(all(np.all(np.abs(_idx(v, "prestretch", PS[3:], k, _lp) - 8) <= 1)
                               for k in ("eta_f_lv", "eta_f_hv")))),
        Row("6.2, fig. 22; 7", "All three indices unchanged by in-plane down-scaling (k = 1-100)",
            lambda v: "largest spread over k = 1, 13, 14, 100: " + ", ".join(
                f"{k} {np.ptp(_idx(v, 'scale', SWEEP_VALUES['scale'], k, lambda x: f'{x:g}')):.1e}"
                for k in ("eta_f_lv", "eta_f_hv", "eta_c")) + " points",
            SWEEP.format("scale", "scale"),
            lambda v: when(all(np.ptp(_idx(v, "scale", SWEEP_VALUES["scale"], k, lambda x: f"{x:g}")) < 0.01
                               for k in ("eta_f_lv", "eta_f_hv", "eta_c"))), "rule: spread below 0.01 points"),
        Row("6.2, fig. 22", "d falls below the air breakdown gap (1.1 mm) beyond a down-scaling of about 13",
            lambda v: f"gap V / (3 kV/mm) = {v['scale.air_gap_mm']:.3f} mm; 15 mm / k reaches it at k = "
                      f"{v['scale.limit_k']:.1f}", SWEEP.format("scale", "scale"),
            lambda v: when(abs(v["scale.air_gap_mm"] - 1.1) <= 0.05 and abs(v["scale.limit_k"] - 13) <= 1),
            "rule: within 0.05 mm and 1"),
        Row("6.2, fig. 23; 7", "Circular and square electrodes of equal area give virtually the same curves",
            lambda v: (f"largest difference, of the curves' maxima: force {v['shape.lv.force_pct']:.2f} % (0 V), "
                       f"{v['shape.hv.force_pct']:.2f} % (eq. 14 HV); dC {v['shape.lv.dc_pct']:.2f} % (0 V), "
                       f"{v['shape.hv.dc_pct']:.2f} % (HV)"),
            "`dea-twin study sweep shape`",
            lambda v: when(max(v[f"shape.{c}.{q}_pct"] for c in ("lv", "hv") for q in ("force", "dc")) < 2),
            "rule: below 2 %"),
    ]
    return rows


ROWS = _rows()


@dataclass(frozen=True)
class Choice:
    """An interpretation the twin makes where the paper leaves room, its alternative, and both numbers."""

    topic: str
    twin: str
    alternative: str
    numbers: Callable[[dict], str]


def _shifts(v: dict, group: str, spacings: tuple) -> str:
    """The alternative's indices at each spacing, and the largest shift from the sweep's."""
    rows = "; ".join(f"d = {d * 1e3:g} mm: " + " / ".join(f"{v[f'{group}.{_mm(d)}.{k}']:.1f}" for k in INDICES)
                     for d in spacings)
    shift = ", ".join(f"{k} {np.max(np.abs(_idx(v, group, spacings, k) - _idx(v, 'spacing', spacings, k))):.2f}"
                      for k in INDICES)
    return f"{rows} % (eta_F,LV / eta_F,HV / eta_C); largest shift from the sweep's: {shift} points"


CHOICES = [
    Choice("\"Neighbours not deflected\" (eqs. 13, 15, 16)", "free units: no indenter, the membrane follows",
           "indenters held at 0 mm (`--undeflected held`)",
           lambda v: "; ".join(
               f"d = {d[:-2]} mm: free {v[f'spacing.{d}.eta_f_lv']:.1f} / {v[f'spacing.{d}.eta_f_hv']:.1f} / "
               f"{v[f'spacing.{d}.eta_c']:.1f} %, held {v[f'held.{d}.eta_f_lv']:.1f} / "
               f"{v[f'held.{d}.eta_f_hv']:.1f} / {v[f'held.{d}.eta_c']:.1f} %" for d in ("1mm", "15mm"))
           + " (eta_F,LV / eta_F,HV / eta_C)"),
    Choice("The \"0 mm\" pre-load of figures 15-16", "neighbours free (as above)",
           "held at 0 mm (`dea-twin study curves --neighbours 0,...`)",
           lambda v: "; ".join(
               f"DE{k} force at 15 mm, lp 1.10: free {v[f'curves.1.10.fmax.DE{k}.free.lv_N']:.3f} N (0 V), "
               f"{v[f'curves.1.10.fmax.DE{k}.free.hv_N']:.3f} N (2730 V); held "
               f"{v[f'curves.1.10.fmax.DE{k}.0mm.lv_N']:.3f} / {v[f'curves.1.10.fmax.DE{k}.0mm.hv_N']:.3f} N"
               for k in (1, 2))),
    Choice("Frame length in the spacing sweep", "L held at 200 mm (Table 1): the short edges are 69 mm from the "
           "electrodes at d = 1 mm, 55 mm at d = 15 mm", "L = 3 D + 2 d + 110 mm: the short edges stay 55 mm away",
           lambda v: _shifts(v, "short_edges_fixed", SPACING_ALTERNATIVES[:-1])),
    Choice("Frame length in the spacing sweep", "as above",
           "L = 3 D + 2 d + 30 mm: b = 15 mm on all four sides (\"b\" read as the distance to every edge)",
           lambda v: _shifts(v, "b_all_sides", SPACING_ALTERNATIVES)),
    Choice("Edge distance b in its sweep", "b through the frame width, H = D + 2 b; L stays 200 mm, so the "
           "short edges stay 55 mm away", "b on all four sides: L = 3 D + 2 d + 2 b as well",
           lambda v: "eta_C at b = 10 / 30 / 50 mm: " + " / ".join(
               f"{v[f'edge_distance.{b}.eta_c']:.1f}" for b in ("10mm", "30mm", "50mm")) + " % (H only), "
           + " / ".join(f"{v[f'all_sides.{b}.eta_c']:.1f}" for b in ("10mm", "30mm", "50mm"))
           + " % (all sides); eta_F,LV " + " / ".join(
               f"{v[f'all_sides.{b}.eta_f_lv']:.1f}" for b in ("10mm", "30mm", "50mm")) + " % (all sides)"),
    Choice("HV of the section-6 indices", "eq. 14, Ec t0 / lp^2 (Ec = 80 V/um)",
           "the experiments' 2730 V",
           lambda v: (f"eta_F,HV {v['base.eta_f_hv']:.2f} % at {v['base.hv_voltage_V']:.0f} V (wrinkling "
                      f"{'flagged' if v['base.hv_wrinkled'] else 'not flagged'}, field above 150 V/um "
                      f"{'flagged' if v['base.hv_field_exceeded'] else 'not flagged'}); "
                      f"{v['hv_experimental.eta_f_hv']:.2f} % at 2730 V (wrinkling "
                      f"{'flagged' if v['hv_experimental.wrinkled'] else 'not flagged'})")),
    Choice("Capacitance change of a test", "from the test's first point (the paper's \"deviation from the initial "
           "value\")", "from the flat pre-stretched membrane at 0 V",
           lambda v: (f"DE2's offset at the start of a test, lp 1.10: {v['curves.1.10.start_offset.hv_pF']:.1f} pF "
                      f"with 2730 V on it, {v['curves.1.10.start_offset.8mm_pF']:.1f} pF with the neighbours at "
                      "8 mm; the section-6 curves start flat at 0 V, where both readings agree")),
]


# ------------------------------------------------------------------- rendering

def _cell(text: str) -> str:
    return text.replace("|", "\\|")


def _figures(v: dict[str, float]) -> list[str]:
    """The twin's numbers of figures 12-16: dC at 15 mm, and the force maxima per pre-load and voltage."""
    lines = []
    for lp, (cap, force) in (("1.10", (12, 15)), ("1.20", (13, 16))):
        hv = v[f"curves.{lp}.hv_V"]
        lines += [f"**lp = {lp}, figure {cap}**: capacitance change at 15 mm [pF], 0 V, neighbours free", "",
                  "| deformed \\ measured | DE1 | DE2 |", "|---|---|---|"]
        lines += [f"| DE{k} | " + " | ".join(f"{v[f'curves.{lp}.dc.DE{k}_deformed.DE{m}_pF']:.2f}" for m in (1, 2))
                  + " |" for k in (1, 2)]
        lines += ["", f"**lp = {lp}, figure {force}**: largest force [N] of the measured DE, LV = 0 V, HV = {hv:.0f} V",
                  "", "| neighbours | DE1, LV | DE1, HV | DE2, LV | DE2, HV |", "|---|---|---|---|---|"]
        for nb, label in (("free", "free (the twin's \"0 mm\")"), ("0mm", "held at 0 mm"), ("4mm", "at 4 mm"),
                          ("6mm", "at 6 mm"), ("8mm", "at 8 mm")):
            lines.append(f"| {label} | " + " | ".join(f"{v[f'curves.{lp}.fmax.DE{k}.{nb}.{x}_N']:.4f}"
                                                     for k in (1, 2) for x in ("lv", "hv")) + " |")
        flagged = v[f"curves.{lp}.flagged"]
        lines += ["", "Wrinkling or a field above 150 V/um: " + ("flagged in some curve (see the study's summary.md)"
                                                              if flagged else "flagged in none of these curves."), ""]
    return lines[:-1]


def render(v: dict[str, float]) -> dict[str, str]:
    """The generated blocks of docs/paper.md: ``comparison``, ``figures``, ``choices``, ``numbers``."""
    comparison = ["| # | section | the paper | the twin | command | verdict |", "|---|---|---|---|---|---|"]
    for i, row in enumerate(ROWS, start=1):
        rule = f" ({row.rule})" if row.rule else ""
        comparison.append(f"| {i} | {row.section} | {_cell(row.paper)} | {_cell(row.twin(v))} | {row.command} "
                          f"| {row.verdict(v)}{rule} |")
    counts = {name: verdicts(v).count(name) for name in (REPRODUCED, NOT, RIG, UNCHECKED)}
    comparison += ["", f"{len(ROWS)} statements: " + ", ".join(f"{n} {name}" for name, n in counts.items()) + "."]
    choices = ["| topic | the twin | the alternative | numbers |", "|---|---|---|---|"]
    choices += [f"| {c.topic} | {_cell(c.twin)} | {_cell(c.alternative)} | {_cell(c.numbers(v))} |" for c in CHOICES]
    mesh = (f"At 15 mm (DE2 swept, neighbours free, 0 V) the coarse mesh ({v['mesh.coarse.elements']:.0f} elements) "
            f"gives a force {v['mesh.coarse_vs_default.force15_pct']:.2f} %, a capacitance "
            f"{v['mesh.coarse_vs_default.cap15_pct']:.3f} % and a capacitance change "
            f"{v['mesh.coarse_vs_default.dc15_pct']:.2f} % away from the default mesh's "
            f"({v['mesh.default.elements']:.0f} elements).")
    numbers = ["| value | number |", "|---|---|"] + [f"| `{k}` | {v[k]:.9g} |" for k in sorted(v)]
    return {"comparison": "\n".join(comparison), "figures": "\n".join(_figures(v)), "choices": "\n".join(choices),
            "mesh": mesh, "numbers": "\n".join(numbers)}


def verdicts(v: dict[str, float]) -> list[str]:
    return [row.verdict(v) for row in ROWS]


BLOCKS = ("comparison", "figures", "choices", "mesh", "numbers")


def _block(name: str) -> re.Pattern:
    return re.compile(f"(<!-- begin {name}: generated by tools/paper_numbers.py -->\n)(.*?)(<!-- end {name} -->)", re.S)


def read_blocks(text: str) -> dict[str, str]:
    """The generated blocks of a docs/paper.md text."""
    out = {}
    for name in BLOCKS:
        match = _block(name).search(text)
        if match is None:
            raise ValueError(f"docs/paper.md has no generated block {name!r}")
        out[name] = match.group(2).rstrip("\n")
    return out


def read_numbers(text: str) -> dict[str, float]:
    """The named values of the ``numbers`` block of a docs/paper.md text."""
    rows = re.findall(r"^\| `([^`]+)` \| ([^|]+) \|$", read_blocks(text)["numbers"], re.M)
    return {key: float(value) for key, value in rows}


def write(path: Path, v: dict[str, float]) -> None:
    text = path.read_text()
    for name, block in render(v).items():
        text, count = _block(name).subn(lambda m, block=block: m.group(1) + block + "\n" + m.group(3), text)
        if count != 1:
            raise ValueError(f"{path} has {count} generated blocks {name!r}, expected 1")
    path.write_text(text)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--mesh", choices=MESHES, default="default")
    parser.add_argument("--steps", type=int, default=15)
    parser.add_argument("--workers", type=int, default=1)
    what = parser.add_mutually_exclusive_group()
    what.add_argument("--write", action="store_true", help=f"rewrite the generated blocks of {DOC}")
    what.add_argument("--check", action="store_true", help=f"compare with the numbers in {DOC}")
    parser.add_argument("--json", type=Path, help="also save the computed values to this JSON file")
    what.add_argument("--rerender", action="store_true",
                      help=f"rewrite the tables of {DOC} from its numbers block (no solving: after a text change)")
    args = parser.parse_args()
    if args.rerender:
        write(DOC, read_numbers(DOC.read_text()))
        return 0
    values = compute(ArrayConfig(**MESHES[args.mesh]), args.steps, args.workers,
                     log=lambda text: print(text, file=sys.stderr))
    if args.json:
        args.json.write_text(json.dumps(values, indent=1, sort_keys=True))
    if args.check:
        docs = read_numbers(DOC.read_text())
        bad = mismatches(docs, values)
        worst = {k: abs(values[k] - docs[k]) / (abs(docs[k]) if relative(k) else 1.0) for k in docs if k in values}
        for key in sorted(worst, key=lambda k: -worst[k] / max(tolerance(k), 1e-12))[:10]:
            print(f"{key}: docs {docs[key]:.6g}, here {values[key]:.6g} (off {worst[key]:.3g}, "
                  f"tolerance {tolerance(key):.3g}{' relative' if relative(key) else ''})")
        print("\n".join(bad) or "every value within its tolerance")
        if verdicts(docs) != verdicts(values):
            print("verdicts differ:", [(i + 1, a, b) for i, (a, b) in enumerate(zip(verdicts(docs), verdicts(values)))
                                       if a != b])
            return 1
        return 1 if bad else 0
    for block in render(values).values():
        print(block + "\n", flush=True)
    if args.write:
        write(DOC, values)
        print(f"paper_numbers: wrote {DOC}", file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main())

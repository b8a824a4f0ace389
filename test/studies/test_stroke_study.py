"""Figures 5-6 (section 3.2) computed: an NBS matched to the nominal curves of unit 2 gives several
times the LBS stroke, and loses stroke when the neighbours are pre-deflected (verification 7).

On the coarse mesh (within 0.1% of the default in force); the numbers of the default mesh are
in docs/actuator.md.  The strokes come from full biased solves; one is checked against the
intersections of driven curves with the bias line found by Brent's method.
"""

import argparse
import csv
import functools

import numpy as np
import pytest
from conftest import COARSE
from scipy.optimize import brentq

from dea_array_twin import ArrayConfig, ArrayTwin
from dea_array_twin.cli import study as study_cli
from dea_array_twin.studies.stroke import stroke_curve_tasks, stroke_study
from dea_array_twin.studies.tasks import run_curve

STEPS = 15


@functools.lru_cache(maxsize=1)
def _study():
    cfg = ArrayConfig(**COARSE)
    return stroke_study(cfg, [run_curve(t) for t in stroke_curve_tasks(cfg, steps=STEPS)])


def test_matched_nbs_gives_several_times_the_lbs_stroke_and_loses_stroke_with_deflected_neighbours():
    result = _study()
    lbs, nbs = result.row("LBS", "free"), result.row("NBS", "free")
    nbs_pre, lbs_pre = result.row("NBS", "pre"), result.row("LBS", "pre")
    assert all(r.stable and not r.snap for r in result.rows)
    assert lbs.rest_position == pytest.approx(0.005, abs=1e-6) == nbs.rest_position  # the design point
    assert nbs.stroke > 5 * lbs.stroke > 0  # coarse mesh: 3.24 vs 0.38 mm
    assert nbs_pre.stroke < 0.85 * nbs.stroke  # 2.49 mm: 77% of nominal
    assert lbs_pre.stroke == pytest.approx(lbs.stroke, rel=0.15)  # the LBS hardly cares
    assert nbs_pre.rest_position > nbs.rest_position + 0.003  # the raised neighbours lift the NBS unit


def test_a_stroke_equals_the_intersections_of_driven_curves_with_the_bias_line():
    """NBS, neighbours pre-deflected: w(0 V) and w(HV) by Brent's method on driven solves of unit 2."""
    result = _study()
    row, law = result.row("NBS", "pre"), result.biases["NBS"]
    twin = ArrayTwin(ArrayConfig(**COARSE))

    def gap(w, voltage):
        return twin.solve([0.008, w, 0.008], [0.0, voltage, 0.0], ["driven"] * 3, check_stability=False).force[1] \
            - law.force(w)

    rest = brentq(gap, row.rest_position - 0.001, row.rest_position + 0.001, args=(0.0,), xtol=1e-12)
    up = brentq(gap, row.position - 0.001, row.position + 0.001, args=(result.voltage,), xtol=1e-12)
    assert row.rest_position == pytest.approx(rest, rel=1e-6)
    assert row.stroke == pytest.approx(up - rest, rel=1e-5)


def test_stroke_study_writes_table_figure_and_summary(tmp_path, coarse_yaml):
    parser = argparse.ArgumentParser()
    study_cli.add_arguments(parser)
    out = tmp_path / "out"
    args = parser.parse_args(["stroke", str(coarse_yaml), "--steps", str(STEPS), "--out", str(out)])
    assert study_cli.run_from_args(args) == 0
    with open(out / "stroke.csv") as f:
        rows = list(csv.DictReader(line for line in f if not line.startswith("#")))
    expected = _study()
    assert [(r["bias"], r["neighbours"]) for r in rows] == [("LBS", "free"), ("LBS", "pre"), ("NBS", "free"),
                                                            ("NBS", "pre")]
    np.testing.assert_allclose([float(r["stroke_m"]) for r in rows], [r.stroke for r in expected.rows], rtol=1e-9)
    assert (out / "stroke.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert "NBS/LBS stroke, neighbours free" in (out / "summary.md").read_text()

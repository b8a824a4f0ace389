"""``dea-twin stroke`` and ``dea-twin simulate``: the exact JSON keys, values equal to the library, errors."""

import csv
import json

import numpy as np
import pytest
import yaml

from dea_array_twin import ArrayConfig, ArrayTwin
from dea_array_twin.cli.main import main
from dea_array_twin.model.response import Schedule, simulate, stroke

CIRCULAR_LBS = {"layout": "circular", "frame_radius": 0.025, "unit_modes": ["biased"],
                "bias": [{"type": "linear", "stiffness": 40.0, "free_position": 0.020}], "mass": 0.005,
                "damping": 0.05}


@pytest.fixture
def lbs_yaml(tmp_path):
    path = tmp_path / "lbs.yaml"
    path.write_text(yaml.safe_dump(CIRCULAR_LBS))
    return path


def test_stroke_json_has_the_exact_keys_and_the_library_values(capsys, lbs_yaml):
    assert main(["stroke", str(lbs_yaml), "--voltage", "0,1000,2730", "--json"]) == 0
    out = json.loads(capsys.readouterr().out)
    assert list(out) == ["voltage", "position", "force", "capacitance", "stable", "snap"]
    curve = stroke(ArrayTwin(ArrayConfig.from_dict(CIRCULAR_LBS)), [0.0, 1000.0, 2730.0])
    assert out["voltage"] == [0.0, 1000.0, 2730.0]
    for key in ("position", "force", "capacitance"):
        assert np.shape(out[key]) == (3, 1)
        np.testing.assert_allclose(out[key], getattr(curve, key), rtol=1e-9)
    assert out["stable"] == [True] * 3 and out["snap"] == [False] * 3
    assert 0.6e-3 < out["position"][2][0] - out["position"][0][0] < 0.8e-3  # the LBS stroke, ~0.69 mm


def test_stroke_table_prints_the_stroke_in_mm(capsys, lbs_yaml):
    assert main(["stroke", str(lbs_yaml), "--voltage", "0,2730"]) == 0
    lines = capsys.readouterr().out.splitlines()
    assert "s1 [mm]" in lines[1] and "stable" in lines[1] and "snap" in lines[1]
    assert float(lines[2].split()[1]) == 0.0 and 0.6 < float(lines[3].split()[1]) < 0.8


def test_stroke_reports_a_snap_on_the_level_it_happens(capsys, tmp_path):
    w = np.linspace(0.0, 0.016, 33)
    cfg = dict(CIRCULAR_LBS, bias=[{"type": "table", "position": w.tolist(),
                                    "force": (0.2035 + 0.08 * np.tanh((w - 0.007) / 0.001)).tolist()}])
    path = tmp_path / "dome.yaml"
    path.write_text(yaml.safe_dump(cfg))
    assert main(["stroke", str(path), "--voltage", "1000,2730,0", "--start", "0.005", "--json"]) == 0
    captured = capsys.readouterr()
    out = json.loads(captured.out)
    assert out["snap"] == [False, True, False] and all(out["stable"])
    assert "snapped through from" in captured.err


def test_stroke_without_biased_units_is_refused_by_name(capsys):
    assert main(["stroke", "--voltage", "0,2730"]) == 2
    assert "stroke needs a biased unit" in capsys.readouterr().err


def test_simulate_json_and_csv_match_the_library(capsys, lbs_yaml, tmp_path):
    args = ["simulate", str(lbs_yaml), "--voltage", "0.004:2730", "--duration", "0.02", "--dt", "0.002"]
    assert main(args + ["--json"]) == 0
    out = json.loads(capsys.readouterr().out)
    assert list(out) == ["time", "position", "velocity", "force", "capacitance"]
    sim = simulate(ArrayTwin(ArrayConfig.from_dict(CIRCULAR_LBS)), Schedule((0.004,), ((2730.0,),)), None, 0.02, 0.002)
    assert out["time"] == pytest.approx(np.arange(11) * 0.002)
    for key in ("position", "velocity", "force", "capacitance"):
        np.testing.assert_allclose(out[key], getattr(sim, key), rtol=1e-9, atol=1e-15)
    assert out["position"][-1][0] > out["position"][0][0] + 1e-4  # it moves up after the voltage step
    assert main(args + ["--out", str(tmp_path / "run")]) == 0
    with open(tmp_path / "run" / "simulate.csv") as f:
        rows = list(csv.reader(f))
    assert rows[0] == ["time_s", "w1_m", "v1_m_per_s", "F1_N", "C1_F", "V1_V", "f1_N"] and len(rows) == 12
    assert float(rows[-1][1]) == pytest.approx(out["position"][-1][0], rel=1e-9)
    assert (tmp_path / "run" / "simulate.png").stat().st_size > 10_000


@pytest.mark.parametrize("schedule, message", [("0:1,2", "expected 1 (one per unit) or 1"),
                                               ("0.5", "expected 'T:v1,v2,...'"),
                                               ("0.2:0;0.1:10", "increasing")])
def test_simulate_refuses_a_bad_schedule(capsys, lbs_yaml, schedule, message):
    try:  # a malformed schedule is an argparse error (SystemExit), a wrong count one of the config
        code = main(["simulate", str(lbs_yaml), "--voltage", schedule, "--duration", "0.01", "--dt", "0.001"])
    except SystemExit as exc:
        code = exc.code
    assert code == 2
    assert message.split("(")[0].strip() in capsys.readouterr().err

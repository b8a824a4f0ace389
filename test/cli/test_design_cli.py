"""``dea-twin design-bias``: the files it writes, read back the way a user does, and its errors."""

import csv
import json

import pytest
import yaml
from conftest import COARSE

from dea_array_twin.cli.main import main
from dea_array_twin.configfile import load_config

CIRCULAR = {"layout": "circular", "frame_radius": 0.025, **COARSE}


@pytest.fixture
def circular_yaml(tmp_path):
    path = tmp_path / "circular.yaml"
    path.write_text(yaml.safe_dump(CIRCULAR))
    return path


def test_design_bias_writes_a_config_that_stroke_solves_to_the_csv_stroke(tmp_path, circular_yaml, capsys):
    out = tmp_path / "design"
    assert main(["design-bias", str(circular_yaml), "--bias", "lbs", "--voltage", "2730", "--out", str(out)]) == 0
    captured = capsys.readouterr()
    assert "design-bias: nominal curves: 2/2" in captured.err  # progress on stderr
    assert "| array-aware | the array, every scenario |" in captured.out
    assert sorted(p.name for p in out.iterdir()) == ["design.yaml", "strokes.csv", "summary.md", "unit_1.png"]
    cfg = load_config(out / "design.yaml")
    assert cfg.modes == ("biased",) and cfg.per_unit("bias")[0].kind == "linear"
    rows = list(csv.DictReader(open(out / "strokes.csv")))
    assert [(r["design"], r["unit"], r["scenario"]) for r in rows] == [("single-alone", "1", "s"),
                                                                         ("single", "1", "s"), ("aware", "1", "s")]
    aware = rows[2]
    start = yaml.safe_load((out / "design.yaml").read_text().split("--start ")[1].split()[0])
    assert main(["stroke", str(out / "design.yaml"), "--voltage", "0,2730", "--start", str(start), "--json"]) == 0
    curve = json.loads(capsys.readouterr().out)
    stroke = curve["position"][1][0] - curve["position"][0][0]
    assert stroke == pytest.approx(float(aware["stroke_m"]), rel=1e-6)
    assert float(aware["stroke_m"]) == pytest.approx(float(aware["predicted_stroke_m"]), rel=0.01)
    assert curve["stable"] == [True, True]


@pytest.mark.parametrize("args, message", [
    (["--units", "4"], "--units must be distinct units in [1, 3]"),
    (["--scenarios", "01"], "must have one character per unit (3)"),
    (["--voltage", "-5"], "--voltage must be a finite voltage > 0 V"),
    (["--position-range", "0,0.05"], "within max_displacement"),
])
def test_design_bias_names_the_bad_argument(args, message, capsys):
    argv = ["design-bias", "--bias", "nbs", "--voltage", "2730", *args]
    assert main(argv) == 2
    assert message in capsys.readouterr().err

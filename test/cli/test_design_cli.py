"""``dea-twin design-bias``: the files it writes, read back the way a user does, and its errors."""

import csv
import json

import pytest
import yaml
from conftest import COARSE, DOME

from dea_array_twin import ArrayTwin
from dea_array_twin.cli.main import main
from dea_array_twin.configfile import load_config
from dea_array_twin.design import optimise
from dea_array_twin.model.response import rest_state

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
    rows = list(csv.DictReader((out / "strokes.csv").read_text().splitlines()))
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


def test_lbs_plus_nbs_on_a_steep_dome_snaps_in_the_full_solves_exit_1_without_allow_snap_0_with_it(
        tmp_path, monkeypatch, capsys):
    """An LBS in parallel with the dome's table, designed on the circular unit.

    The full solves of the design snap through from 0 V to V (a fold the inner model's
    load steps stepped over): without ``--allow-snap`` the command warns and exits 1;
    with it, it exits 0 and reports the snap.  The design it writes, read back by the
    config loader and solved with ``ArrayTwin.solve`` from its rest state, gives the
    CSV's stroke and its snap.  The optimiser's effort is cut (8 candidates per parameter,
    8 generations) to keep the two designs cheap: what is checked is the full solves."""
    monkeypatch.setattr(optimise, "POPULATION", 8)
    monkeypatch.setattr(optimise, "GENERATIONS", 8)
    config = tmp_path / "dome.yaml"
    config.write_text(yaml.safe_dump({**CIRCULAR, "unit_modes": ["biased"], "bias": [DOME]}))
    argv = ["design-bias", str(config), "--bias", "lbs+nbs", "--voltage", "2730", "--out"]
    assert main([*argv, str(tmp_path / "strict")]) == 1
    strict = capsys.readouterr().out
    assert "| array-aware | the array, every scenario |" in strict and "snap-through not allowed" in strict
    assert "Warning: the full solves of the array-aware design snap through" in strict
    assert main([*argv, str(tmp_path / "snap"), "--allow-snap"]) == 0
    allowed = capsys.readouterr().out
    assert "snap-through allowed" in allowed and "snap through where the inner model saw no snap" not in allowed
    assert "does not return to its low state" in allowed  # the dome is bistable: once snapped up it stays
    rows = csv.DictReader((tmp_path / "snap" / "strokes.csv").read_text().splitlines())
    aware = [r for r in rows if r["design"] == "aware"]
    assert len(aware) == 1 and aware[0]["snapped"] == "True" and aware[0]["stable"] == "True"
    text = (tmp_path / "snap" / "design.yaml").read_text()
    start = float(text.split("--start ")[1].split()[0])
    twin = ArrayTwin(load_config(tmp_path / "snap" / "design.yaml"))
    low = rest_state(twin, start=start)
    high = twin.solve(voltage=[2730.0], check_stability=True)
    assert low.stable and high.stable and not low.snaps and high.snaps
    assert high.position[0] - low.position[0] == pytest.approx(float(aware[0]["stroke_m"]), rel=1e-6)
    assert float(aware[0]["stroke_m"]) == pytest.approx(float(aware[0]["predicted_stroke_m"]), rel=0.01)


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

"""The dea-twin command line: curve and solve, JSON in SI units, clear errors."""

import json
import subprocess
import sys

import numpy as np
import pytest

from dea_array_twin import ArrayTwin
from dea_array_twin.cli.main import main


def test_curve_json_has_one_row_per_step_and_matches_the_library(capsys):
    assert main(["curve", "--unit", "2", "--to", "0.012", "--steps", "4", "--voltage", "2730", "--json"]) == 0
    out = json.loads(capsys.readouterr().out)
    assert out["unit"] == 2
    assert out["displacement"] == pytest.approx([0, 0.003, 0.006, 0.009, 0.012])
    assert np.shape(out["force"]) == (5, 3) and np.shape(out["capacitance"]) == (5, 3)
    twin = ArrayTwin()
    for d, force, cap in zip(out["displacement"], out["force"], out["capacitance"]):
        res = twin.solve([0, d, 0], [0, 2730, 0], ("free", "driven", "free"))
        assert force == pytest.approx(res.force.tolist(), rel=1e-8, abs=1e-12)
        assert cap == pytest.approx(res.capacitance.tolist(), rel=1e-9)
    assert out["force"][0][1] == pytest.approx(0.0, abs=1e-9)
    assert out["force"][-1][0] == 0.0 and out["force"][-1][1] > 0.2


def test_curve_with_predeflected_neighbours_drives_them(capsys):
    assert main(["curve", "--to", "0.006", "--steps", "2", "--neighbours", "0.008", "--json"]) == 0
    out = json.loads(capsys.readouterr().out)
    forces = np.array(out["force"])
    assert np.all(forces[:, 0] > 0) and np.all(forces[:, 2] > 0)  # neighbours held at 8 mm
    assert forces[0, 1] < 0  # the raised neighbours lift unit 2: it must be pulled down


def test_curve_table_is_labelled(capsys):
    assert main(["curve", "--to", "0.003", "--steps", "1"]) == 0
    lines = capsys.readouterr().out.splitlines()
    assert "d [mm]" in lines[0] and "F2 [N]" in lines[0] and "C3 [pF]" in lines[0]
    assert len(lines) == 3


def test_solve_json_reports_state_and_flags(capsys):
    assert main(["solve", "--displacement", "0,0.01,0", "--voltage", "0,2730,0", "--modes", "free,driven,free",
                 "--json"]) == 0
    out = json.loads(capsys.readouterr().out)
    assert out["modes"] == ["free", "driven", "free"]
    assert out["force"][0] == 0.0 and out["force"][1] > 0
    assert out["stable"] is True and out["warnings"] == []


def test_bad_config_file_exits_2_naming_the_field(tmp_path, capsys):
    bad = tmp_path / "bad.yaml"
    bad.write_text("spacing: -0.002\n")
    assert main(["curve", str(bad)]) == 2
    err = capsys.readouterr().err
    assert "spacing" in err and "overlap" in err
    assert main(["curve", str(tmp_path / "missing.yaml")]) == 2
    assert "cannot read config file" in capsys.readouterr().err
    assert main(["curve", "--unit", "4"]) == 2
    assert "--unit must be in [1, 3]" in capsys.readouterr().err


def test_no_equilibrium_exits_1_with_the_reason(capsys):
    assert main(["solve", "--displacement", "0,0.005,0", "--voltage", "0,10000,0", "--modes", "free,driven,free"]) == 1
    assert "failed to converge" in capsys.readouterr().err


def test_module_entry_point_runs_in_a_subprocess():
    proc = subprocess.run([sys.executable, "-m", "dea_array_twin.cli.main", "solve", "--displacement", "0,0.002,0",
                           "--json"], capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0, proc.stderr
    assert json.loads(proc.stdout)["force"][1] > 0


def test_demo_runs_the_twin_with_the_wave_controller():
    """The README's first command: within seconds the wave deflects the units in turn."""
    import os

    from domain_coordinator import domain_id

    with domain_id() as domain:
        env = dict(os.environ, ROS_DOMAIN_ID=str(domain), ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST")
        proc = subprocess.run([sys.executable, "-m", "dea_array_twin.cli.main", "demo", "--duration", "7"], env=env,
                              capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0, proc.stderr
    rows = [line for line in proc.stdout.splitlines()[1:] if "|" in line]
    deflections = np.array([[float(cell.split()[0]) for cell in row.split("|")[1:]] for row in rows])
    assert len(rows) >= 10
    # Sampled twice a second, so peaks of the 8 mm ramps are seen only roughly: > 5 mm.
    first_up = [int(np.argmax(deflections[:, k] > 5.0)) for k in (0, 1)]
    assert deflections[:, 0].max() > 5.0 and deflections[:, 1].max() > 5.0
    assert first_up[0] < first_up[1]  # unit 1 first, then unit 2
    assert "unit 2 triggered by capacitance" in proc.stderr

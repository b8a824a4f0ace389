"""The dea-twin command line: curve and solve, JSON in SI units, clear errors."""

import json
import subprocess
import sys

import numpy as np
import pytest
from conftest import run_until_then_interrupt

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
    """``--neighbours 0.008``: units 1 and 3 held at 8 mm while unit 2 is swept, as the library gives it."""
    assert main(["curve", "--to", "0.006", "--steps", "2", "--neighbours", "0.008", "--json"]) == 0
    forces = np.array(json.loads(capsys.readouterr().out)["force"])
    twin = ArrayTwin()
    for d, row in zip((0.0, 0.003, 0.006), forces):
        res = twin.solve([0.008, d, 0.008], 0.0, ("driven",) * 3)
        # another load path: both converged to residual_tol t0 c10 D = 1.8e-9 N
        np.testing.assert_allclose(row, res.force, rtol=0, atol=2e-8)
    assert forces[0, 1] < -0.01  # the raised neighbours lift unit 2: it must be pulled down


def test_curve_table_is_labelled_in_mm_n_and_pf_with_the_json_values(capsys):
    assert main(["curve", "--to", "0.003", "--steps", "1", "--json"]) == 0
    curve = json.loads(capsys.readouterr().out)
    assert main(["curve", "--to", "0.003", "--steps", "1"]) == 0
    lines = capsys.readouterr().out.splitlines()
    assert lines[0].split() == ["d", "[mm]", "F1", "[N]", "F2", "[N]", "F3", "[N]", "C1", "[pF]", "C2", "[pF]",
                                "C3", "[pF]"]
    table = np.array([line.split() for line in lines[1:]], dtype=float)
    assert table.shape == (2, 7)
    expected = np.column_stack([np.array(curve["displacement"]) * 1e3, curve["force"],
                                np.array(curve["capacitance"]) * 1e12])
    np.testing.assert_allclose(table, expected, atol=1e-6)  # printed with 6 decimals


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
    proc = subprocess.run([sys.executable, "-m", "dea_array_twin.cli", "solve", "--displacement", "0,0.002,0",
                           "--json"], capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0, proc.stderr
    res = ArrayTwin().solve([0, 0.002, 0], 0.0, ("driven",) * 3)
    np.testing.assert_allclose(json.loads(proc.stdout)["force"], res.force, rtol=1e-12, atol=1e-15)


def test_demo_runs_the_twin_with_the_wave_controller():
    """The README's first command: the wave deflects unit 1, then unit 2 on its capacitance trigger.

    Read as it runs, with a generous deadline (a loaded machine runs the wave slower),
    then stopped with SIGINT, which ends it cleanly.
    """
    def deflections(lines):
        rows = [line for line in lines if line.count("|") == 3 and not line.startswith("t [s]")]
        return np.array([[float(cell.split()[0]) for cell in row.split("|")[1:]] for row in rows]).reshape(-1, 3)

    def unit_2_up_after_unit_1(lines):
        d = deflections(lines)
        # sampled twice a second, so peaks of the 8 mm ramps are seen only roughly: > 5 mm
        up = [np.flatnonzero(d[:, k] > 5.0) for k in (0, 1)]
        return up[0].size > 0 and up[1].size > 0 and any("unit 2 triggered by capacitance" in x for x in lines)

    output, done, code = run_until_then_interrupt([sys.executable, "-m", "dea_array_twin.cli", "demo", "--duration",
                                                   "0"], unit_2_up_after_unit_1, timeout=90)
    assert code == 0, f"exit code {code} after SIGINT: {output.lines[-40:]}"
    assert done, "".join(output.lines[-40:])
    d = deflections(output.lines)
    first_up = [int(np.argmax(d[:, k] > 5.0)) for k in (0, 1)]
    assert first_up[0] < first_up[1]  # unit 1 first, then unit 2
    assert d.max() < 8.0 + 1e-6  # never beyond the wave's 8 mm amplitude


def test_version_is_the_installed_distributions(capsys):
    from importlib.metadata import version

    with pytest.raises(SystemExit) as exit_info:
        main(["--version"])
    assert exit_info.value.code == 0
    assert capsys.readouterr().out.strip() == f"dea-twin {version('dea_array_twin')}"


def test_bag_recover_onto_its_own_source_exits_2_and_leaves_it_alone(tmp_path, capsys):
    bag = tmp_path / "run.mcap"
    bag.write_bytes(b"\x89MCAP0\r\n not really")
    assert main(["bag-recover", str(bag), str(tmp_path / "." / "run.mcap")]) == 2
    err = capsys.readouterr().err
    assert "must differ from the source" in err and "Traceback" not in err
    assert bag.read_bytes() == b"\x89MCAP0\r\n not really"

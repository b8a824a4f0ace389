"""Calibration of the Yeoh coefficients: Nelder-Mead recovery, confidence hint, data files, CLI.

Twins use a coarse mesh (344 P2 elements): a 9-point 0-15 mm sweep of the middle unit
takes about 0.1-0.15 s, one cost evaluation of two curves about 0.3 s.
"""

import argparse
import csv
import itertools
import math
import time

import numpy as np
import pytest
import yaml
from conftest import COARSE, FREE_CENTRE

from dea_array_twin import ArrayConfig, ArrayTwin, ConvergenceError
from dea_array_twin.bag.series import csv_header
from dea_array_twin.calibration import data as calibration_data
from dea_array_twin.calibration import yeoh
from dea_array_twin.calibration.measured import MeasuredCurve, simulate
from dea_array_twin.calibration.yeoh import fit_yeoh, gauss_newton_errors
from dea_array_twin.cli import calibrate as calibration_cli
from dea_array_twin.model.metrics import fit

TABLE1 = np.array([0.18e6, 10.84e3, -0.11e3])  # c10, c20, c30 [Pa]
PNG_MAGIC = b"\x89PNG\r\n\x1a\n"


def coarse(**changes) -> ArrayConfig:
    return ArrayConfig(**COARSE, **changes)


def sweep(cfg: ArrayConfig, voltage: float = 0.0, samples: int = 9) -> tuple[np.ndarray, np.ndarray]:
    """Commands of the middle unit swept 0-15 mm at ``voltage`` [V], neighbours free."""
    d = np.zeros((samples, 3))
    d[:, 1] = np.linspace(0.0, 0.015, samples)
    v = np.zeros((samples, 3))
    v[:, 1] = voltage
    return d, v


def twin_curve(name: str, cfg: ArrayConfig, voltage: float = 0.0, samples: int = 9) -> MeasuredCurve:
    """A curve whose 'measured' force is the twin's at ``cfg`` (noiseless)."""
    d, v = sweep(cfg, voltage, samples)
    placeholder = MeasuredCurve(name, cfg, FREE_CENTRE, d, v, 1, force=np.zeros(samples))
    force = simulate(ArrayTwin(cfg), placeholder)[0][:, 1]
    return MeasuredCurve(name, cfg, FREE_CENTRE, d, v, 1, force=force)


def parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="dea-twin calibrate")
    calibration_cli.add_arguments(p)
    return p


def calibrate(*argv: str) -> int:
    return calibration_cli.run_from_args(parser().parse_args([str(a) for a in argv]))


def write_csv(path, curve: MeasuredCurve, extra_rows=(), comment="# synthetic sweep\n"):
    """``curve`` in the replay CSV format (force on the curve's unit only, other F cells empty)."""
    n = curve.config.n_units
    with open(path, "w", newline="") as f:
        f.write(comment)
        writer = csv.writer(f)
        writer.writerow(csv_header(n))
        for i in range(curve.n_samples):
            force = ["" if k != curve.unit else repr(float(curve.force[i])) for k in range(n)]
            writer.writerow([0.5 * i, *map(repr, curve.displacement[i].tolist()), *map(repr, curve.voltage[i].tolist()),
                             *force, *[""] * n])
        for row in extra_rows:
            writer.writerow(row)
    return path


# ------------------------------------------------------------------- recovery

def test_nelder_mead_recovers_table1_coefficients_from_noisy_curves_at_two_prestretches():
    """Two noisy sweeps (lp 1.10 and 1.20) "measured" on the default mesh and fitted on
    the coarse one (model error), started 40 % off in c10: the truth is found.

    Noise: Gaussian, 0.5 % of each curve's largest force, fixed seed.  Model error: the
    coarse mesh's force is 0.16 % off the default mesh's, a bias well inside the noise.
    With 2 x 9 samples the Gauss-Newton standard error of c10 is about 0.7 % (c10
    correlates at -0.9 with c20, which trades off against it), so the 2 % tolerance on
    c10 is about 3 standard errors.  ``tol=3e-3`` stops the simplex at 750 Pa, below
    every standard error.  About 80 evaluations of 0.3 s: 25 s on an idle core.
    """
    rng = np.random.default_rng(20240611)
    truth = [twin_curve(f"lp {lp:.2f}", ArrayConfig(prestretch=lp)) for lp in (1.10, 1.20)]
    clean = [MeasuredCurve(c.name, coarse(prestretch=c.config.prestretch), c.modes, c.displacement, c.voltage,
                           c.unit, force=c.force) for c in truth]
    noisy = [MeasuredCurve(c.name, c.config, c.modes, c.displacement, c.voltage, c.unit,
                           force=c.force + rng.normal(0.0, 0.005 * c.force.max(), c.n_samples)) for c in clean]
    tic = time.perf_counter()
    result = fit_yeoh(noisy, start=(0.25e6, 5e3, 0.0), max_evaluations=300, tol=3e-3)
    elapsed = time.perf_counter() - tic
    print(f"recovery: {result.values} +- {result.stderr} Pa, FIT {result.fit}, {result.n_evaluations} evaluations "
          f"({result.failed_evaluations} failed), {elapsed:.1f} s")

    assert result.converged, result.message
    assert abs(result.c10 - TABLE1[0]) < 0.02 * TABLE1[0]
    assert np.all(np.abs(result.values - TABLE1) < 3 * result.stderr)
    assert result.stderr[0] < 0.01 * TABLE1[0]  # c10 well determined
    assert "c30" in result.poorly_determined and "c10" not in result.poorly_determined
    assert np.all(result.initial_fit < 50) and np.all(result.fit > 98)
    assert result.cost == pytest.approx(np.sum((1 - result.fit / 100) ** 2), rel=1e-9)
    assert result.cost < result.initial_cost
    for curve, model, value in zip(noisy, result.model_force, result.fit):
        assert fit(curve.force, model) == pytest.approx(value)
    for curve in clean:  # the fitted model against the noiseless truth
        refit = simulate(ArrayTwin(result.config(curve.config)), curve)[0][:, 1]
        assert fit(curve.force, refit) > 99.0
    assert result.config(coarse(prestretch=1.2)).prestretch == 1.2
    assert result.config(coarse()).c10 == result.c10


class LinearModel:
    """Stand-in for the twin: force = c10 t + c20 t^2 + c30 t^3 on the swept unit, t = d / 15 mm.

    Raises ConvergenceError where c20 > ``fail_above``, as the twin does where the
    membrane has no equilibrium.
    """

    def __init__(self, fail_above: float = math.inf):
        self.fail_above = fail_above
        self.failures = 0

    def simulate(self, twin: ArrayConfig, curve: MeasuredCurve):
        if twin.c20 > self.fail_above:
            self.failures += 1
            raise ConvergenceError("no equilibrium (stand-in)")
        t = curve.displacement[:, 1] / 0.015
        force = np.zeros_like(curve.displacement)
        force[:, curve.unit] = 1e-6 * (twin.c10 * t + twin.c20 * t**2 + twin.c30 * t**3)
        return force, np.zeros_like(force)


def linear_curves(model: LinearModel, truth, noise: float, rng) -> list[MeasuredCurve]:
    cfg = ArrayConfig()
    curves = []
    for samples in (11, 15):
        d, v = sweep(cfg, samples=samples)
        clean = MeasuredCurve("x", cfg, FREE_CENTRE, d, v, 1, force=np.zeros(samples))
        force = model.simulate(cfg.replace(c10=truth[0], c20=truth[1], c30=truth[2]), clean)[0][:, 1]
        curves.append(MeasuredCurve(f"{samples} samples", cfg, FREE_CENTRE, d, v, 1,
                                    force=force + rng.normal(0, noise, samples)))
    return curves


def test_standard_errors_match_linear_least_squares_when_the_force_is_linear_in_the_coefficients(monkeypatch):
    """With a model linear in (c10, c20, c30) the Gauss-Newton errors are the exact OLS ones."""
    model = LinearModel()
    monkeypatch.setattr(yeoh, "ArrayTwin", lambda cfg: cfg)
    monkeypatch.setattr(yeoh, "simulate", model.simulate)
    truth = np.array([0.18e6, 40e3, -20e3])
    curves = linear_curves(model, truth, 0.002, np.random.default_rng(7))
    result = fit_yeoh(curves, start=(0.3e6, 0.0, 0.0), tol=1e-7, max_evaluations=2000)
    assert result.converged

    # the same problem as weighted linear least squares: rows scaled by 1/||F - mean F||
    rows, rhs = [], []
    for c in curves:
        t = c.displacement[:, 1] / 0.015
        spread = np.linalg.norm(c.force - c.force.mean())
        rows.append(1e-6 * np.column_stack([t, t**2, t**3]) / spread)
        rhs.append(c.force / spread)
    a, b = np.vstack(rows), np.concatenate(rhs)
    best, ssr, *_ = np.linalg.lstsq(a, b, rcond=None)
    cov = ssr[0] / (len(b) - 3) * np.linalg.inv(a.T @ a)
    np.testing.assert_allclose(result.values, best, rtol=1e-4, atol=1e-3 * np.sqrt(np.diag(cov)).max())
    np.testing.assert_allclose(result.stderr, np.sqrt(np.diag(cov)), rtol=1e-4)
    np.testing.assert_allclose(result.correlation, cov / np.sqrt(np.outer(np.diag(cov), np.diag(cov))), atol=1e-6)


def test_points_without_equilibrium_or_with_c10_below_zero_cost_a_penalty_not_a_crash(monkeypatch):
    model = LinearModel(fail_above=5e3)
    monkeypatch.setattr(yeoh, "ArrayTwin", lambda cfg: cfg)
    monkeypatch.setattr(yeoh, "simulate", model.simulate)
    truth = np.array([2e3, 3e3, 5e3])  # c10 near 0: the simplex steps across c10 = 0 on its way
    curves = linear_curves(model, truth, 0.0, np.random.default_rng(0))
    progress = []
    result = fit_yeoh(curves, start=(0.1e6, 0.0, 0.0), tol=1e-6, max_evaluations=3000,
                      progress=lambda n, cost, best: progress.append((n, cost, best)))
    assert result.converged
    np.testing.assert_allclose(result.values, truth, rtol=1e-3)
    assert result.failed_evaluations > model.failures > 0  # the rest had c10 <= 0
    failures = sum(1 for _, cost, _ in progress if cost == yeoh.FAILED_COST)
    assert failures == result.failed_evaluations
    assert [n for n, _, _ in progress] == list(range(1, result.n_evaluations + 1))
    assert all(b2 <= b1 for (_, _, b1), (_, _, b2) in itertools.pairwise(progress))  # best never rises

    with pytest.raises(ConvergenceError):  # an unusable start is an error, not a penalty
        fit_yeoh(curves, start=(0.1e6, 6e3, 0.0))


def test_singular_normal_matrix_gives_infinite_standard_errors():
    t = np.linspace(0, 1, 10)
    collinear = np.column_stack([t, 2 * t, t**2])  # columns 1 and 2 cannot be told apart
    stderr, corr = gauss_newton_errors(collinear, np.full(10, 0.01))
    assert np.all(np.isinf(stderr)) and np.isnan(corr[0, 1]) and np.all(np.diag(corr) == 1)
    stderr, _ = gauss_newton_errors(np.column_stack([t, np.zeros(10), t**2]), np.full(10, 0.01))
    assert np.all(np.isinf(stderr))
    stderr, _ = gauss_newton_errors(np.column_stack([t, t**2, t**3])[:3], np.zeros(3))  # N = p
    assert np.all(np.isinf(stderr))
    stderr, _ = gauss_newton_errors(np.column_stack([t, t**2, t**3]), np.full(10, 0.01))
    assert np.all(np.isfinite(stderr)) and np.all(stderr > 0)


# ------------------------------------------------------------------------ FIT

# ------------------------------------------------------------------ bad data

@pytest.mark.parametrize("name, text, expected", [
    ("empty.csv", "# only a comment\n\n", ["no header line"]),
    ("numbers.csv", "0,0,0.01,0,1.0\n", ["line 1", "no header line"]),
    ("word.csv", "d1_m,d2_m,d3_m,F2_N\n0,0,0,0\n0,abc,0,0.1\n0,0.02,0,0.2\n",
     ["line 3", "column 2 (d2_m)", "'abc' is not a number"]),
    ("nan.csv", "d1_m,d2_m,d3_m,V2_V,F2_N\n0,0,0,0,0\n0,0.01,0,nan,0.1\n0,0.02,0,0,0.2\n",
     ["line 3", "column 4 (V2_V)", "not finite"]),
    ("no_d3.csv", "time_s,d1_m,d2_m,F2_N\n0,0,0,0\n1,0,0.01,0.1\n2,0,0.02,0.2\n", ["no column d3_m", "3 unit(s)"]),
    ("d4.csv", "d1_m,d2_m,d3_m,d4_m,F2_N\n0,0,0,0,0\n", ["column 4 (d4_m)", "unit 4", "3 unit(s)"]),
    ("no_force.csv", "d1_m,d2_m,d3_m,C2_F\n0,0,0,1e-10\n0,0.01,0,2e-10\n0,0.02,0,3e-10\n", ["no force column"]),
    ("two.csv", "d1_m,d2_m,d3_m,F2_N\n0,0,0,0\n0,0.01,0,0.1\n0,0.02,0,\n",
     ["column 4 (F2_N)", "2 measured sample(s)", "at least 3"]),
    ("ragged.csv", "d1_m,d2_m,d3_m,F2_N\n0,0,0,0\n0,0.01,0\n", ["line 3", "3 cells", "4 columns"]),
])
def test_bad_csv_files_exit_2_naming_file_line_and_column(tmp_path, capsys, coarse_yaml, name, text, expected):
    path = tmp_path / name
    path.write_text(text)
    assert calibrate(path, "--config", coarse_yaml) == 2
    err = capsys.readouterr().err
    assert str(path) in err and "Traceback" not in err
    for phrase in expected:
        assert phrase in err


def test_missing_files_and_non_mcap_bags_exit_2(tmp_path, capsys):
    assert calibrate(tmp_path / "missing.csv") == 2
    assert "cannot read" in (err := capsys.readouterr().err) and "missing.csv" in err
    assert calibrate(tmp_path / "missing.mcap") == 2
    assert "no such file" in capsys.readouterr().err
    fake = tmp_path / "notes.mcap"
    fake.write_text("time_s,d1_m\n0,0\n")
    assert calibrate(fake) == 2
    assert "not an MCAP file" in capsys.readouterr().err
    ok = tmp_path / "ok.csv"
    ok.write_text("d1_m,d2_m,d3_m,F2_N\n0,0,0,0\n0,0.01,0,0.1\n0,0.02,0,0.2\n")
    assert calibrate(ok, "--modes", "free,driven") == 2
    assert "--modes must be 3 values" in capsys.readouterr().err
    assert calibrate(ok, "--max-evaluations", "0") == 2
    assert "--max-evaluations" in capsys.readouterr().err


# ----------------------------------------------------------- CSV and MCAP in

def test_csv_round_trip_through_the_cli_writes_table_yaml_and_png(tmp_path, capsys, coarse_yaml):
    """A replay-format CSV of a twin sweep, fitted from a start 10 % off for 4 evaluations
    (too few to converge, which the command says): the files hold what the library's fit
    of the same data from the same start gives, and eq. 12 of their own columns."""
    cfg = coarse(prestretch=1.2)
    curve = twin_curve("truth", cfg, voltage=1500.0, samples=7)
    (tmp_path / "lp12.yaml").write_text(yaml.safe_dump({**COARSE, "prestretch": 1.2}))
    unmeasured = [3.5, 0.0, 0.004, 0.0, 0.0, 1500.0, 0.0, "", "", "", "", "", ""]  # empty F2: not in the curve
    data = write_csv(tmp_path / "run.csv", curve, extra_rows=[unmeasured])
    out = tmp_path / "result"
    start = TABLE1 * [1.1, 0.9, 1.0]
    assert calibrate(f"{data}@{tmp_path / 'lp12.yaml'}", "--config", coarse_yaml, "--modes", "free,driven,free",
                     "--start", ",".join(map(str, start)), "--max-evaluations", "4", "--out", out) == 0
    stdout, err = capsys.readouterr()
    assert "c10" in stdout and "run.csv unit 2" in stdout and f"wrote {out}" in stdout
    assert "lp12.yaml" in err and "raise --max-evaluations" in err  # 4 evaluations cannot converge
    library = fit_yeoh([curve], start=start, max_evaluations=4)

    with open(out / "calibration.csv", newline="") as f:
        rows = list(csv.DictReader(f))
    assert len(rows) == curve.n_samples  # the row without a force is left out
    measured = np.array([float(r["measured_force_N"]) for r in rows])
    model = np.array([float(r["model_force_N"]) for r in rows])
    np.testing.assert_array_equal(measured, curve.force)
    np.testing.assert_allclose(model, library.model_force[0], rtol=1e-12, atol=1e-15)
    np.testing.assert_array_equal([float(r["swept_displacement_m"]) for r in rows], curve.displacement[:, 1])
    assert {r["swept_unit"] for r in rows} == {"2"} and {r["unit"] for r in rows} == {"2"}

    snippet = yaml.safe_load((out / "fit.yaml").read_text())
    fitted = ArrayConfig.from_dict(snippet["config"])  # a valid config snippet
    np.testing.assert_allclose([fitted.c10, fitted.c20, fitted.c30], library.values, rtol=1e-12)
    assert not np.allclose(library.values, TABLE1, rtol=1e-3)  # 4 evaluations are not the truth
    assert set(snippet["stderr"]) == {"c10", "c20", "c30"}
    assert snippet["fit_percent"][0]["curve"] == "run.csv unit 2"
    assert snippet["fit_percent"][0]["fitted"] == pytest.approx(fit(measured, model), abs=1e-6)
    assert snippet["fit_percent"][0]["fitted"] == pytest.approx(library.fit[0], abs=1e-6)
    assert snippet["converged"] is False and snippet["evaluations"] == 4

    png = (out / "calibration.png").read_bytes()
    assert png.startswith(PNG_MAGIC) and len(png) > 10_000


def test_an_mcap_recording_gives_the_same_curve_as_the_equivalent_csv(tmp_path, coarse_yaml):
    """Commands every 0.5 s, the node's answer 0.05 s later, a stale output 0.01 s after each command."""
    from rclpy.serialization import serialize_message
    from std_msgs.msg import Float64MultiArray

    from dea_array_twin.bag.twin_config import metadata_from_config
    from dea_array_twin.bag.writer import Ros2McapWriter

    cfg = coarse()
    rng = np.random.default_rng(3)
    d, v = sweep(cfg, voltage=1200.0, samples=6)
    d[:, 0] = 0.002  # a free neighbour's command: kept, not used by the twin
    force = np.zeros((6, 3))
    force[:, 1] = np.linspace(0.0, 0.3, 6) + rng.normal(0, 1e-3, 6)
    t0 = 1_700_000_000_000_000_000

    def at(seconds: float) -> int:
        return t0 + round(seconds * 1e9)

    def floats(values) -> bytes:
        return serialize_message(Float64MultiArray(data=[float(x) for x in values]))

    bag = tmp_path / "rig.mcap"
    metadata = {"dea_array_twin_config": metadata_from_config(cfg, FREE_CENTRE)}
    with Ros2McapWriter(bag, metadata=metadata, flush_period=None) as rec:
        disp = rec.add_topic("/array/command/displacement", "std_msgs/msg/Float64MultiArray")
        volt = rec.add_topic("/array/command/voltage", "std_msgs/msg/Float64MultiArray")
        out = rec.add_topic("/array/force", "std_msgs/msg/Float64MultiArray")
        rec.write(volt, floats(v[0]), at(0.0))
        for i in range(6):
            rec.write(disp, floats(d[i]), at(0.001 + 0.5 * i))
            rec.write(out, floats(force[i - 1] if i else np.zeros(3)), at(0.011 + 0.5 * i))  # not yet updated
            rec.write(out, floats(force[i]), at(0.051 + 0.5 * i))

    csv_curve = MeasuredCurve("csv", cfg, FREE_CENTRE, d, v, 1, force=force[:, 1])
    from_csv, _ = calibration_data.load_curves([str(write_csv(tmp_path / "rig.csv", csv_curve))], str(coarse_yaml),
                                              list(FREE_CENTRE), 0.1)
    from_bag, notes = calibration_data.load_curves([str(bag)], None, None, 0.04)
    assert len(from_bag) == len(from_csv) == 1  # free units give no curve
    a, b = from_bag[0], from_csv[0]
    assert (a.name, b.name) == ("rig.mcap unit 2", "rig.csv unit 2")
    assert a.config == b.config and a.modes == b.modes == FREE_CENTRE and a.unit == b.unit == 1
    np.testing.assert_array_equal(a.displacement, b.displacement)
    np.testing.assert_array_equal(a.voltage, b.voltage)
    np.testing.assert_array_equal(a.force, b.force)
    assert any("6 of 12 force message(s)" in n for n in notes)
    driven, notes = calibration_data.load_curves([str(bag)], None, ["driven"] * 3, 0.04)
    assert [c.name for c in driven] == ["rig.mcap unit 2"]  # units 1 and 3 were not measured (force 0)
    assert sum("does not vary" in n for n in notes) == 2

    with pytest.raises(calibration_data.DataError, match="at least 3"):  # default settle: the answers are too early
        calibration_data.load_curves([str(bag)], None, None, calibration_data.DEFAULT_SETTLE)

    commands_only = tmp_path / "commands.mcap"
    with Ros2McapWriter(commands_only, metadata=metadata, flush_period=None) as rec:
        disp = rec.add_topic("/command/displacement", "std_msgs/msg/Float64MultiArray")
        rec.write(disp, floats(d[1]), at(0.0))
    with pytest.raises(calibration_data.DataError, match="no force topic"):
        calibration_data.load_curves([str(commands_only)], None, None, 0.1)


def test_slip_option_fits_gamma_to_csv_capacitance_curves_and_writes_its_files(tmp_path, capsys, coarse_yaml):
    """``--slip`` on the replay CSV format: C{k}_F columns, a cross curve with the
    measured unit free.  Noiseless data from gamma = (1, 0.95) at (0, 15 mm): the fit
    must find 0.95 to 0.005 (test_slip.py tests noisy recovery of the core)."""
    truth = coarse(slip_displacement=(0.0, 0.015), slip_factor=(1.0, 0.95))
    modes = ("driven", "free", "free")
    d = np.zeros((7, 3))
    d[:, 0] = np.linspace(0.0, 0.015, 7)
    placeholder = MeasuredCurve("cross", truth, modes, d, np.zeros_like(d), 1, capacitance=np.zeros(7))
    _, cap = simulate(ArrayTwin(truth), placeholder)
    path = tmp_path / "cross.csv"
    with open(path, "w", newline="") as f:
        writer = csv.writer(f)
        writer.writerow(csv_header(3))
        for i in range(7):
            writer.writerow([i, *d[i], 0, 0, 0, "", "", "", *cap[i]])
    out = tmp_path / "slip"
    assert calibrate(path, "--config", coarse_yaml, "--modes", "driven,free,free", "--slip", "0,0.015",
                     "--max-evaluations", "30", "--out", out) == 0
    fitted = yaml.safe_load((out / "slip.yaml").read_text())
    assert fitted["config"]["slip_displacement"] == [0.0, 0.015]
    assert fitted["config"]["slip_factor"][1] == pytest.approx(0.95, abs=0.005)
    assert {row["curve"] for row in fitted["fit_percent"]} == {"cross.csv unit 1", "cross.csv unit 2",
                                                               "cross.csv unit 3"}
    assert (out / "slip.png").read_bytes()[:8] == PNG_MAGIC
    with open(out / "slip.csv") as f:
        rows = list(csv.DictReader(f))
    assert len(rows) == 3 * 7
    assert "FIT [%] of the capacitance change" in capsys.readouterr().out
    assert calibrate(path, "--config", coarse_yaml, "--slip", "0,0.015", "--start", "1,2,3", "--out", out) == 2
    assert "--start sets Yeoh coefficients" in capsys.readouterr().err
    with pytest.raises(SystemExit) as stop:  # one knot is not a table
        calibrate(path, "--config", coarse_yaml, "--slip", "0.01", "--out", out)
    assert stop.value.code == 2

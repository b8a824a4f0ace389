"""``dea-twin rom train`` and ``rom info``: a validated ROM file, its summary, clear errors."""

import dataclasses

import numpy as np

from dea_array_twin import ArrayConfig
from dea_array_twin.cli.main import main
from dea_array_twin.configfile import load_config
from dea_array_twin.model.reduced import config_hash
from dea_array_twin.romfile import load_rom, save_rom


def test_rom_train_writes_a_validated_rom_of_the_config_and_info_shows_it(coarse_yaml, tmp_path, capsys):
    out = tmp_path / "small.npz"
    code = main(["rom", "train", str(coarse_yaml), "--out", str(out), "--snapshots", "8", "--modes", "5",
                 "--validation", "3", "--displacement-range", "0,0.004", "--voltage-range", "0,1000",
                 "--unit-modes", "free,driven,free", "--tolerance", "0.05", "--calibration", "4", "--edges", "0.5"])
    printed = capsys.readouterr().out
    assert code == 0, printed
    rom = load_rom(out, load_config(coarse_yaml))
    assert rom.config_hash == config_hash(load_config(coarse_yaml)) != config_hash(ArrayConfig())
    assert rom.envelope.modes == ("free", "driven", "free") and rom.n_modes == 5
    np.testing.assert_allclose(rom.envelope.displacement_max, [np.nan, 0.004, np.nan])
    np.testing.assert_allclose(rom.envelope.voltage_max, [1000.0] * 3)
    table = rom.validation
    assert table["snapshots"] == 8 and table["commands"] == 3
    assert table["force_error_max"] <= 0.05 and table["capacitance_error_max"] <= 0.05
    assert "validation on 3 held-out commands" in printed and f"{table['force_error_max']:.3%}" in printed
    assert main(["rom", "info", str(out)]) == 0
    captured = capsys.readouterr()
    info = captured.out
    assert rom.config_hash in info and "5 POD modes" in info and "8 snapshots" in info
    assert table["edges"] == 0.5 and "50% of the commands dense at the envelope's bounds" in info
    assert table["calibration_commands"] == 4 and f"scaled by {rom.indicator_scale:.3g}, calibrated on 4" in info
    assert "warning" not in captured.err
    loose = dataclasses.replace(rom, validation=dict(table, capacitance_error_max=0.08, over_tolerance=1,
                                                     over_tolerance_unflagged=1))
    assert main(["rom", "info", str(save_rom(loose, tmp_path / "loose"))]) == 0
    assert "warning: its validation found errors above its tolerance 5.000%" in capsys.readouterr().err


def test_rom_train_refuses_bad_options_and_rom_info_a_missing_file(tmp_path, capsys):
    assert main(["rom", "train", "--out", str(tmp_path / "x.npz"), "--tolerance", "2"]) == 2
    assert "--tolerance must be in (0, 1)" in capsys.readouterr().err
    assert main(["rom", "train", "--out", str(tmp_path / "x.npz"), "--displacement-range", "0,0.05"]) == 2
    assert "max_displacement" in capsys.readouterr().err
    assert main(["rom", "train", "--out", str(tmp_path / "x.npz"), "--calibration", "-1"]) == 2
    assert "--calibration must be >= 0" in capsys.readouterr().err
    assert main(["rom", "train", "--out", str(tmp_path / "x.npz"), "--edges", "1.5"]) == 2
    assert "--edges must be a share in [0, 1]" in capsys.readouterr().err
    assert main(["rom", "train", "--out", str(tmp_path / "no" / "x.npz")]) == 2
    assert "does not exist" in capsys.readouterr().err
    assert main(["rom", "info", str(tmp_path / "missing.npz")]) == 2
    assert "does not exist" in capsys.readouterr().err

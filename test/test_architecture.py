"""The package's layers and code checks as tests, so CI fails when they break.

``lint-imports`` checks the contracts in ``.importlinter`` (the layers cli > studies |
calibration | replay > ros > bag > configfile > model, a model free of ROS, bag,
plotting, Dask and YAML libraries, and no import circles); ``ruff`` the rule set in
``ruff.toml``.  Both run from the repository root on the source tree.
"""

import shutil
import subprocess
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]


def _tool(name: str) -> str:
    path = Path(sys.executable).parent / name
    if path.exists():
        return str(path)
    found = shutil.which(name)
    if found is None:
        pytest.fail(f"{name} is not installed: pip install 'dea_array_twin[test]'")
    return found


def test_import_contracts_hold():
    proc = subprocess.run([_tool("lint-imports"), "--no-cache"], cwd=REPO, capture_output=True, text=True,
                          timeout=120)
    assert proc.returncode == 0, proc.stdout + proc.stderr
    assert "0 broken" in proc.stdout


def test_a_model_module_importing_rclpy_breaks_the_contracts(tmp_path):
    """The contracts really bind: a copy of the package whose model imports rclpy fails them."""
    shutil.copytree(REPO / "dea_array_twin", tmp_path / "dea_array_twin")
    shutil.copy(REPO / ".importlinter", tmp_path / ".importlinter")
    with open(tmp_path / "dea_array_twin" / "model" / "material.py", "a") as f:
        f.write("\nimport rclpy  # noqa: E402,F401\n")
    proc = subprocess.run([_tool("lint-imports"), "--no-cache"], cwd=tmp_path, capture_output=True, text=True,
                          timeout=120)
    assert proc.returncode != 0
    assert "dea_array_twin.model.material -> rclpy" in proc.stdout


def test_ruff_finds_nothing():
    proc = subprocess.run([_tool("ruff"), "check", "--no-cache", "."], cwd=REPO, capture_output=True, text=True,
                          timeout=120)
    assert proc.returncode == 0, proc.stdout + proc.stderr

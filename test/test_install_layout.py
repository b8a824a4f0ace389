"""The installed layout that ROS 2 tools rely on.

These check the package as installed into the running interpreter's prefix
(``sys.prefix``, the venv made by ``tools/setup.sh``): the ament index marker,
the share directory with ``package.xml``, the ``dea-twin`` console script in
``bin/`` and the launcher in ``lib/dea_array_twin/`` where ``ros2 run`` looks.
They skip when the package is not installed there (e.g. tests run from a source
tree only, or a colcon install prefix that is not ``sys.prefix``).
"""

import importlib.metadata
import os
import subprocess
import sys
import sysconfig
import xml.etree.ElementTree as ET
from pathlib import Path

import pytest
from conftest import run_until_then_interrupt

PACKAGE = 'dea_array_twin'
EXECUTABLE = 'dea-twin'
PREFIX = Path(sys.prefix)


@pytest.fixture(scope='module', autouse=True)
def installed_in_prefix() -> importlib.metadata.Distribution:
    """Skip the module unless the distribution is installed in this interpreter's prefix."""
    try:
        importlib.metadata.distribution(PACKAGE)
    except importlib.metadata.PackageNotFoundError:
        pytest.skip(f'{PACKAGE} is not installed (run tools/setup.sh)')
    # `python -m pytest` puts the repo root on sys.path, where a source-tree
    # *.egg-info left by a build would also be found: look in the prefix only.
    site_dirs = sorted({sysconfig.get_path('purelib'), sysconfig.get_path('platlib')})
    dists = list(importlib.metadata.distributions(name=PACKAGE, path=site_dirs))
    if not dists:
        pytest.skip(f'{PACKAGE} is not installed in {sys.prefix} (only elsewhere on sys.path)')
    return dists[0]


def test_ament_index_marks_package_and_share_holds_its_package_xml():
    marker = PREFIX / 'share' / 'ament_index' / 'resource_index' / 'packages' / PACKAGE
    assert marker.is_file(), f'missing ament index marker {marker}'

    package_xml = PREFIX / 'share' / PACKAGE / 'package.xml'
    assert package_xml.is_file(), f'missing {package_xml}'
    root = ET.parse(package_xml).getroot()
    assert root.tag == 'package'
    assert root.findtext('name') == PACKAGE
    assert root.findtext('export/build_type') == 'ament_python'


def test_ament_index_finds_share_directory_in_prefix(monkeypatch):
    packages = pytest.importorskip('ament_index_python.packages',
                                   reason='ament_index_python is not installed')
    monkeypatch.setenv('AMENT_PREFIX_PATH', str(PREFIX))
    share = packages.get_package_share_directory(PACKAGE)
    assert Path(share) == PREFIX / 'share' / PACKAGE


def test_console_script_is_in_bin_next_to_interpreter():
    script = Path(sys.executable).parent / EXECUTABLE
    assert script.is_file(), f'missing console script {script}'
    assert os.access(script, os.X_OK), f'{script} is not executable'


def test_ros2_run_launcher_runs_installed_console_script(tmp_path):
    # `ros2 run dea_array_twin dea-twin` executes <prefix>/lib/dea_array_twin/dea-twin.
    launcher = PREFIX / 'lib' / PACKAGE / EXECUTABLE
    assert launcher.is_file(), f'missing {launcher}'
    assert os.access(launcher, os.X_OK), f'{launcher} is not executable'
    result = subprocess.run([str(launcher), '--help'], cwd=tmp_path, capture_output=True,
                            text=True, timeout=120)
    assert result.returncode == 0, result.stderr


@pytest.mark.parametrize('executable', ['twin_node', 'wave_controller'])
def test_ros2_run_finds_the_node_executables(executable):
    # `ros2 run dea_array_twin twin_node` looks only in <prefix>/lib/dea_array_twin/.
    for path in (PREFIX / 'lib' / PACKAGE / executable, Path(sys.executable).parent / executable):
        assert path.is_file() and os.access(path, os.X_OK), f'missing executable {path}'


def test_installed_twin_node_starts_and_stops_on_sigint(tmp_path):
    """The lib/ launcher runs the real node: it logs that it is ready, and SIGINT ends it with 0."""
    output, ready, code = run_until_then_interrupt(
        [str(PREFIX / 'lib' / PACKAGE / 'twin_node'), '--ros-args', '-p', 'update_rate:=20.0'],
        lambda lines: any('ready' in line for line in lines), timeout=60, cwd=tmp_path)
    assert ready, f'twin_node not ready within 60 s (exit code {code} after SIGINT): {output.lines}'
    assert code == 0, f'exit code {code} after SIGINT: {output.lines}'

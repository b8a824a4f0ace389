"""The launch files start what the package really has, with parameters the node really declares.

``launch_ros`` needs ``composition_interfaces``, which has no PyPI wheel, so the launch
files cannot run here (DESIGN.md section 4).  Instead each is loaded with small stand-ins
for ``launch`` and ``launch_ros`` that record what the file asks for; the shipped params
file is checked against the node's declared parameters.
"""

import importlib.util
import re
import sys
import types
from pathlib import Path

import pytest
import yaml

from dea_array_twin.ros.testing import TwinHarness

REPO = Path(__file__).resolve().parents[2]
LAUNCH_FILES = sorted((REPO / "launch").glob("*.launch.py"))


class _Recorded:
    """Stands in for any launch class: keeps its arguments."""

    def __init__(self, *args, **kwargs):
        self.args, self.kwargs = args, kwargs


def _stub(name: str, **classes) -> types.ModuleType:
    module = types.ModuleType(name)
    for attr, base in classes.items():
        setattr(module, attr, type(attr, (base,), {}))
    return module


def _load(path: Path, monkeypatch) -> list:
    """The actions of ``generate_launch_description()`` of the launch file at ``path``."""
    modules = {
        "launch": _stub("launch", LaunchDescription=_Recorded),
        "launch.actions": _stub("launch.actions", DeclareLaunchArgument=_Recorded, IncludeLaunchDescription=_Recorded),
        "launch.substitutions": _stub("launch.substitutions", LaunchConfiguration=_Recorded),
        "launch.launch_description_sources": _stub("launch.launch_description_sources",
                                                   PythonLaunchDescriptionSource=_Recorded),
        "launch_ros": _stub("launch_ros"),
        "launch_ros.actions": _stub("launch_ros.actions", Node=_Recorded),
    }
    for name, module in modules.items():
        monkeypatch.setitem(sys.modules, name, module)
    monkeypatch.setenv("AMENT_PREFIX_PATH", sys.prefix)
    spec = importlib.util.spec_from_file_location(path.stem.replace(".", "_"), path)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module.generate_launch_description().args[0]


def _console_scripts() -> set[str]:
    text = (REPO / "setup.py").read_text()
    return set(re.findall(r"'([\w-]+)': 'dea_array_twin\.[\w.]+:main'", text))


@pytest.fixture(scope="module")
def declared_parameters() -> set[str]:
    from conftest import COARSE

    with TwinHarness(parameters=dict(COARSE, marker_rate=0.0)) as h:
        return set(h.twin_node.list_parameters([], 0).names)


def test_there_are_two_launch_files_installed_to_share():
    names = [p.name for p in LAUNCH_FILES]
    assert names == ["twin.launch.py", "twin_with_controller.launch.py"]
    installed = Path(sys.prefix) / "share" / "dea_array_twin" / "launch"
    if not installed.is_dir():
        pytest.skip("the package is not installed in this prefix (run tools/setup.sh)")
    assert sorted(p.name for p in installed.glob("*.launch.py")) == names


@pytest.mark.parametrize("path", LAUNCH_FILES, ids=lambda p: p.name)
def test_launch_file_starts_the_packages_executables_with_a_params_file_and_namespace(path, monkeypatch,
                                                                                     declared_parameters):
    installed = Path(sys.prefix) / "share" / "dea_array_twin"
    if not (installed / "config" / "twin.yaml").is_file():
        pytest.skip("the package is not installed in this prefix (run tools/setup.sh)")
    actions = _load(path, monkeypatch)
    arguments = {a.args[0]: a.kwargs for a in actions if type(a).__name__ == "DeclareLaunchArgument"}
    nodes = [a.kwargs for a in actions if type(a).__name__ == "Node"]
    assert {"namespace", "params_file"} <= set(arguments)
    assert arguments["params_file"]["default_value"] == str(installed / "config" / "twin.yaml")
    for node in nodes:
        assert node["package"] == "dea_array_twin" and node["executable"] in _console_scripts()
        assert node["namespace"].args == ("namespace",)
    twin = [n for n in nodes if n["executable"] == "twin_node"]
    if twin:
        assert twin[0]["name"] == "dea_array_twin"
        for entry in twin[0]["parameters"]:
            if isinstance(entry, dict):
                assert set(entry) <= declared_parameters
            else:
                assert entry.args == ("params_file",)
    else:  # the controller launch includes the twin's
        include = next(a for a in actions if type(a).__name__ == "IncludeLaunchDescription")
        assert include.args[0].args[0] == str(installed / "launch" / "twin.launch.py")
        assert dict(include.kwargs["launch_arguments"]).keys() == {"namespace", "params_file"}


def test_the_shipped_params_file_sets_only_parameters_the_node_declares(declared_parameters):
    params = yaml.safe_load((REPO / "config" / "twin.yaml").read_text())["/**"]["ros__parameters"]
    assert set(params) <= declared_parameters, set(params) - declared_parameters

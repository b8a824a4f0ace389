"""The node's parameters of actuator mode: per-unit fields flattened, a table bias only from the config file."""

import pytest
import yaml
from conftest import COARSE

from dea_array_twin import ArrayConfig, ArrayTwin, ConfigError
from dea_array_twin.model.bias import LinearBias, TableBias
from dea_array_twin.ros.params import config_from_parameters, config_parameters
from dea_array_twin.ros.testing import TwinHarness

TABLE = {"type": "table", "position": [0.0, 0.005, 0.010, 0.020], "force": [0.2, 0.21, 0.22, 0.24]}


def test_per_unit_fields_flatten_to_one_entry_per_unit_and_back():
    base = ArrayConfig(unit_modes=["free", "biased", "biased"], mass=0.004, contact=[False, True, False],
                       bias=[None, TABLE, {"type": "linear", "stiffness": -20.0, "free_position": 0.001}])
    params = config_parameters(base)
    assert params["unit_modes"] == ["free", "biased", "biased"] and params["mass"] == [0.004] * 3
    assert params["bias.type"] == ["none", "table", "linear"]
    assert params["bias.stiffness"] == [0.0, 0.0, -20.0] and params["bias.free_position"] == [0.0, 0.0, 0.001]
    assert "bias" not in params
    params["bias.stiffness"] = [0.0, 0.0, -25.0]
    cfg = config_from_parameters(params, base)
    assert cfg.per_unit("bias")[1] == TableBias((0.0, 0.005, 0.010, 0.020), (0.2, 0.21, 0.22, 0.24))
    assert cfg.per_unit("bias")[2] == LinearBias(-25.0, 0.001)
    assert cfg.per_unit("contact") == (False, True, False)
    params["bias.type"] = ["table", "table", "linear"]
    with pytest.raises(ConfigError, match=r"^bias.type\[0\]: a table bias comes only from the config file"):
        config_from_parameters(params, base)


def test_node_starts_with_biased_units_from_its_config_file_and_lists_every_parameter(tmp_path):
    path = tmp_path / "array.yaml"
    path.write_text(yaml.safe_dump({**COARSE, "unit_modes": ["free", "biased", "free"], "bias": [TABLE]}))
    with TwinHarness(parameters={"update_rate": 20.0, "config_file": str(path), "bias.force": [0.0, 0.0, 0.3],
                                 "bias.type": ["none", "table", "constant"]}) as h:
        node = h.twin_node
        names = set(node.list_parameters([], 10).names)  # what `ros2 param list` shows
        assert {"unit_modes", "mass", "damping", "contact", "bias.type", "bias.stiffness", "bias.free_position",
                "bias.force"} <= names
        assert node.get_parameter("unit_modes").value == ["free", "biased", "free"]
        assert node.get_parameter("bias.type").value == ["none", "table", "constant"]
        states = h.wait_for("unit_states", lambda m: m.position[1] > 0.001, timeout=30)
    twin = ArrayTwin(ArrayConfig.from_dict({**COARSE, "unit_modes": ["free", "biased", "free"], "bias": [TABLE]}))
    expected = twin.solve(voltage=0.0)
    assert states.position[1] == pytest.approx(expected.position[1], rel=1e-6)
    assert states.effort[1] == pytest.approx(TableBias(*map(tuple, (TABLE["position"], TABLE["force"]))).force(
        states.position[1]), rel=1e-6)

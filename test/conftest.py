"""Shared test settings: the coarse mesh of the findings tests and the usual unit modes.

Meshes are cached by the library per geometry, so building a twin of a geometry seen
before costs milliseconds.
"""

import pytest
import yaml

from dea_array_twin import ArrayConfig, ArrayTwin

#: Unit 2 driven, its neighbours free: the paper's "neighbours not deflected".
FREE_CENTRE = ("free", "driven", "free")
#: A coarse mesh (344 P2 elements on the default array), within 0.1 % of the default in
#: force and capacitance and fast enough for tests that solve many curves.
COARSE = {"mesh_size": 20e-3, "mesh_size_indenter": 2.5e-3, "mesh_size_electrode": 5e-3}


@pytest.fixture
def make_twin():
    """``make_twin(settings=None, **config_changes)`` -> a fresh ArrayTwin."""

    def make(settings=None, **changes):
        return ArrayTwin(ArrayConfig(**changes), settings)

    return make


@pytest.fixture
def coarse_yaml(tmp_path):
    """A config YAML of the default array on the coarse mesh."""
    path = tmp_path / "coarse.yaml"
    path.write_text(yaml.safe_dump(COARSE))
    return path

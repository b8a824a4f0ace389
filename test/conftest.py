"""Shared fixtures: twins are expensive to mesh, so build each configuration once."""

import functools

import pytest

from dea_array_twin import ArrayConfig, ArrayTwin

FREE_CENTRE = ("free", "driven", "free")


@functools.lru_cache(maxsize=None)
def _config(**changes) -> ArrayConfig:
    return ArrayConfig(**changes)


@pytest.fixture
def make_twin():
    """``make_twin(**config_changes)`` -> a fresh ArrayTwin (meshes are cached per process)."""

    def make(settings=None, **changes):
        return ArrayTwin(_config(**changes), settings)

    return make

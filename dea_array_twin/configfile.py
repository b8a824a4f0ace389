"""Reading :class:`~dea_array_twin.model.config.ArrayConfig` from YAML files."""

from __future__ import annotations

from pathlib import Path

import yaml

from .model.config import ArrayConfig, ConfigError


def load_config(path: str | Path | None) -> ArrayConfig:
    """Load a config YAML (a mapping of field: value; missing fields keep defaults).

    ``None`` gives the built-in default (the paper's 1-by-3 array).  A file that
    cannot be read, is not a mapping or holds an unknown or out-of-range field
    raises :class:`ConfigError` naming the file and the field.
    """
    if path is None:
        return ArrayConfig()
    path = Path(path)
    try:
        data = yaml.safe_load(path.read_text())
    except OSError as exc:
        raise ConfigError(f"cannot read config file {path}: {exc.strerror}") from None
    except yaml.YAMLError as exc:
        raise ConfigError(f"config file {path} is not valid YAML: {exc}") from None
    if data is None:
        data = {}
    if not isinstance(data, dict):
        raise ConfigError(f"config file {path} must hold a mapping of field: value, got {type(data).__name__}")
    try:
        return ArrayConfig.from_dict(data)
    except ConfigError as exc:
        raise ConfigError(f"{path}: {exc}") from None


"""The twin's config and unit modes as a bag records them, and the config a replay uses.

The twin's recorder stores them in the metadata record ``dea_array_twin_config``
(:data:`~.writer.CONFIG_RECORD`): every :class:`~dea_array_twin.model.config.ArrayConfig` field as
``str(value)`` (lists and mappings, e.g. ``bias``, as YAML flow text), with ``unit_modes``
the node's modes (``"[driven, free, driven]"``), plus ``update_rate``.
:func:`metadata_from_config` writes that record, :func:`config_from_metadata` reads it
back, and :func:`resolve_config` chooses between a config file, the record and the
default config, and likewise for the unit modes.
"""

from __future__ import annotations

from collections.abc import Sequence

import yaml

from ..configfile import load_config
from ..model.config import ArrayConfig, ConfigError
from ..model.membrane import DRIVEN, check_modes
from .reader import Bag
from .writer import CONFIG_RECORD

__all__ = ["config_from_metadata", "metadata_from_config", "resolve_config"]

NON_CONFIG_KEYS = ("unit_modes", "update_rate")
#: Metadata record of a ``dea-twin replay`` output: its source bag and time origin.
REPLAY_METADATA = "dea_array_twin_replay"


def config_from_metadata(values: dict[str, str]) -> tuple[ArrayConfig, list[str] | None, list[str]]:
    """The config and unit modes of a ``dea_array_twin_config`` metadata record.

    Returns
    -------
    config : ArrayConfig
    modes : list of str or None
        ``unit_modes`` if recorded.
    ignored : list of str
        Keys that are neither config fields nor node parameters (skipped).

    Raises
    ------
    ConfigError
        A field is out of range or unparsable.
    """
    parsed = {}
    for key, text in values.items():
        try:
            parsed[key] = yaml.safe_load(text)
        except yaml.YAMLError:
            parsed[key] = text
    modes = parsed.pop("unit_modes", None)
    for key in NON_CONFIG_KEYS:
        parsed.pop(key, None)
    known = set(ArrayConfig().to_dict())
    ignored = sorted(set(parsed) - known)
    cfg = ArrayConfig.from_dict({k: v for k, v in parsed.items() if k in known})
    if modes is not None and not isinstance(modes, list):
        raise ConfigError(f"unit_modes: expected a list like [driven, free], got {values.get('unit_modes')!r}")
    return cfg, None if modes is None else [str(m) for m in modes], ignored


def metadata_from_config(cfg: ArrayConfig, modes: Sequence[str], update_rate: float = 0.0) -> dict[str, str]:
    """The ``dea_array_twin_config`` record for ``cfg`` (the inverse of :func:`config_from_metadata`)."""
    out = {k: yaml.safe_dump(v, default_flow_style=True, width=10**9).strip() if isinstance(v, (list, dict)) else str(v)
           for k, v in cfg.to_dict().items()}
    out["unit_modes"] = "[" + ", ".join(modes) + "]"
    out["update_rate"] = str(float(update_rate))
    return out


def resolve_config(bag: Bag, config_path: str | None,
                   modes: Sequence[str] | None) -> tuple[ArrayConfig, tuple[str, ...], list[str]]:
    """Config and unit modes for a replay, and where each came from (notes for stderr).

    Config: ``config_path``, else the bag's metadata, else the default.  Modes:
    ``modes``, else the bag's metadata, else all driven.

    Raises
    ------
    ConfigError
        Bad config file, bad recorded config, or modes of the wrong length or value.
    """
    notes = []
    recorded = bag.metadata(CONFIG_RECORD)
    recorded_modes = None
    if recorded is not None:
        try:
            recorded_cfg, recorded_modes, ignored = config_from_metadata(recorded)
        except ConfigError as exc:
            if config_path is None:
                raise ConfigError(f"the config recorded in {bag.path} is invalid ({exc}); pass --config") from None
            recorded_cfg, ignored = None, []
    if config_path is not None:
        cfg = load_config(config_path)
        notes.append(f"config from {config_path}")
    elif recorded is not None:
        cfg = recorded_cfg
        notes.append(f"config from the bag's '{CONFIG_RECORD}' metadata")
        if ignored:
            notes.append(f"warning: ignoring unknown recorded config keys {ignored} (another version of the twin?)")
    else:
        cfg = ArrayConfig()
        notes.append("no config in the bag and no --config: using the default ArrayConfig (the paper's 1-by-3 array)")
    n = cfg.n_units
    if modes is not None:
        source = "--modes"
    elif recorded_modes is not None and len(recorded_modes) == n:
        modes, source = recorded_modes, "the bag's metadata"
    else:
        if recorded_modes is not None:
            notes.append(f"warning: recorded unit_modes {recorded_modes} do not fit {n} units; ignored")
        modes, source = [DRIVEN] * n, "default (all driven)"
    try:
        modes = check_modes(modes, n)
    except ValueError as exc:
        raise ConfigError(f"unit {exc} (from {source})") from None
    notes.append(f"unit modes {', '.join(modes)} from {source}")
    return cfg, modes, notes

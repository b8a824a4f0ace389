"""Reading and writing reduced-order models (:class:`~dea_array_twin.model.reduced.ReducedModel`) as ``.npz``.

The file holds the arrays of :meth:`ReducedModel.to_arrays` (no pickled objects: it is
read with ``allow_pickle=False``), including the training config, its hash, the
envelope and the validation table.
"""

from __future__ import annotations

import zipfile
from pathlib import Path

import numpy as np

from .model.config import ArrayConfig
from .model.reduced import ReducedModel, RomMismatchError, check_config


class RomFileError(ValueError):
    """A ROM file cannot be read (missing, not an ``.npz``, incomplete)."""


def save_rom(rom: ReducedModel, path: str | Path) -> Path:
    """Write ``rom`` to ``path`` (compressed ``.npz``; the suffix is added if missing) and return the path."""
    path = Path(path)
    if path.suffix != ".npz":
        path = path.with_name(path.name + ".npz")
    np.savez_compressed(path, **rom.to_arrays())
    return path


def load_rom(path: str | Path, config: ArrayConfig | None = None) -> ReducedModel:
    """Read a ROM file; with ``config``, refuse a ROM trained on another configuration.

    Raises
    ------
    RomFileError
        The file cannot be read or lacks arrays.
    RomMismatchError
        ``config`` is not the training configuration (the message names the fields
        that differ), or the file has another format version.
    """
    path = Path(path)
    try:
        with np.load(path, allow_pickle=False) as data:
            arrays = {name: data[name] for name in data.files}
    except FileNotFoundError:
        raise RomFileError(f"ROM file {path} does not exist") from None
    except (OSError, ValueError, zipfile.BadZipFile) as exc:
        raise RomFileError(f"cannot read ROM file {path}: {exc}") from None
    try:
        rom = ReducedModel.from_arrays(arrays)
    except RomMismatchError as exc:
        raise RomFileError(f"{path}: {exc}") from None
    if config is not None:
        try:
            check_config(rom, config)
        except RomMismatchError as exc:
            raise RomMismatchError(f"ROM file {path}: {exc}") from None
    return rom

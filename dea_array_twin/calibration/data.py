"""Measured curves from files: the CSV format ``dea-twin replay`` writes, and MCAP bags.

Used by ``dea-twin calibrate``.  A CSV file has the columns ``time_s`` (optional, not
read: rows are applied in file order), ``d{k}_m`` for every unit (held indenter
displacement [m]), optionally ``V{k}_V`` (voltage [V], default 0) and the measured
``F{k}_N`` (force [N]) and/or ``C{k}_F`` (capacitance [F]) of any unit; an empty cell
is "not measured in this row", lines starting with ``#`` are comments.  Every unit
with a measured column of the fitted signal is one :class:`~.measured.MeasuredCurve`.
"""

from __future__ import annotations

import csv
import math
import re
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from ..bag.reader import Bag
from ..bag.series import csv_header
from ..bag.twin_config import resolve_config
from ..configfile import load_config
from ..model.config import ArrayConfig, ConfigError
from ..model.membrane import DRIVEN, FREE, check_modes
from .measured import MeasuredCurve

__all__ = ["DataError", "load_curves", "read_bag", "read_csv"]

DEFAULT_SETTLE = 0.1  # s
_COLUMN = re.compile(r"^(d|V|F|C)(\d+)_(m|V|N|F)$")
_SUFFIX = {"d": "m", "V": "V", "F": "N", "C": "F"}
#: The fitted signal: force (Yeoh fit) or capacitance (slip fit).
_SIGNAL = {"F": "force", "C": "capacitance"}


class DataError(ValueError):
    """A data file cannot be used; the message names the file and, where it applies, line and column."""


# ------------------------------------------------------------------------ CSV

def _table(path: Path) -> tuple[int, list[str], list[tuple[int, list[str]]]]:
    """Header line number, header cells and ``(line number, cells)`` of the data rows."""
    try:
        text = path.read_text()
    except OSError as exc:
        raise DataError(f"cannot read {path}: {exc.strerror or exc}") from None
    lines = [(i, line) for i, line in enumerate(text.splitlines(), start=1)
             if line.strip() and not line.lstrip().startswith("#")]
    expected = ", ".join(csv_header(1))
    if not lines:
        raise DataError(f"{path}: no header line (expected column names like {expected})")
    parsed = [(i, [cell.strip() for cell in row]) for i, row in
              ((i, next(csv.reader([line]))) for i, line in lines)]
    header_line, header = parsed[0]
    if all(_number(cell) is not None for cell in header):
        raise DataError(f"{path} line {header_line}: no header line, the first line that is not a '#' comment "
                        f"holds numbers (expected column names like {expected})")
    for i, cells in parsed[1:]:
        if len(cells) != len(header):
            raise DataError(f"{path} line {i}: {len(cells)} cells, but the header (line {header_line}) "
                            f"has {len(header)} columns")
    return header_line, header, parsed[1:]


def _number(cell: str) -> float | None:
    try:
        return float(cell)
    except ValueError:
        return None


def _columns(path: Path, line: int, header: list[str], n: int,
             signal: str) -> tuple[dict[tuple[str, int], int], list[str]]:
    """``{(kind, unit 0-based): column index}`` of the known columns, and the ignored names."""
    where = f"{path} line {line}"
    found: dict[tuple[str, int], int] = {}
    ignored = []
    for j, name in enumerate(header):
        match = _COLUMN.match(name)
        if name == "time_s":
            continue
        if not match or _SUFFIX[match[1]] != match[3]:
            ignored.append(name)
            continue
        kind, unit = match[1], int(match[2])
        if not 1 <= unit <= n:
            raise DataError(f"{where}, column {j + 1} ({name}): unit {unit}, but the config has {n} unit(s)")
        if (kind, unit - 1) in found:
            raise DataError(f"{where}, column {j + 1} ({name}): duplicate column")
        found[kind, unit - 1] = j
    missing = [f"d{k + 1}_m" for k in range(n) if ("d", k) not in found]
    if missing:
        raise DataError(f"{where}: no column {', '.join(missing)}: the config has {n} unit(s), so the "
                        f"displacement columns d1_m..d{n}_m are required")
    if not any(kind == signal for kind, _ in found):
        what = "force column (F1_N..F{n}_N)" if signal == "F" else "capacitance column (C1_F..C{n}_F)"
        raise DataError(f"{where}: no {what.format(n=n)}: this fit needs measured "
                        f"{_SIGNAL[signal]}s")
    return found, ignored


def _values(path: Path, header: list[str], rows: list[tuple[int, list[str]]], column: int,
            measured: bool, limit: float = math.inf) -> np.ndarray:
    """One column as floats: commands finite and within ``limit``; measurements may be empty or nan (not measured)."""
    out = np.empty(len(rows))
    for r, (line, cells) in enumerate(rows):
        cell = cells[column]
        value = math.nan if measured and cell == "" else _number(cell)
        where = f"{path} line {line}, column {column + 1} ({header[column]})"
        if value is None:
            raise DataError(f"{where}: {cell!r} is not a number")
        if math.isinf(value) or (not measured and math.isnan(value)):
            raise DataError(f"{where}: {cell!r} is not finite" + ("" if measured else "; commands must be"))
        if abs(value) > limit:
            raise DataError(f"{where}: {cell} m is beyond the config's max_displacement ({limit} m)")
        out[r] = value
    return out


def read_csv(path: str | Path, cfg: ArrayConfig, modes: Sequence[str],
             signal: str = "F") -> tuple[list[MeasuredCurve], list[str]]:
    """The curves of a CSV file, one per unit with a column of ``signal``.

    ``signal`` is ``"F"`` (force curves, for the Yeoh fit) or ``"C"`` (capacitance
    curves, for the slip fit).  Rows are applied in file order (``time_s`` is not
    read).  A row whose ``F{k}_N`` (``C{k}_F``) cell is empty (or ``nan``) is left out
    of unit k's curve; a column with no value, or a force column of a free unit
    (force 0 by definition), gives no curve.  Columns of the other signal are not used.

    Returns
    -------
    curves : list of MeasuredCurve
    notes : list of str
        Columns ignored, force columns skipped.

    Raises
    ------
    DataError
        Missing file, no header, displacement columns not matching the config's units,
        a non-numeric cell or a non-finite command, no force column, a force curve with
        fewer than 3 samples or a constant one.
    """
    path = Path(path)
    n = cfg.n_units
    line, header, rows = _table(path)
    found, ignored = _columns(path, line, header, n, signal)
    notes = [f"{path}: ignoring column(s) {', '.join(ignored)}"] if ignored else []
    limit = cfg.scaled("max_displacement")
    d = np.column_stack([_values(path, header, rows, found["d", k], False, limit) for k in range(n)])
    v = np.column_stack([_values(path, header, rows, found["V", k], False) if ("V", k) in found
                         else np.zeros(len(rows)) for k in range(n)])
    curves = []
    for k in sorted(k for kind, k in found if kind == signal):
        values = _values(path, header, rows, found[signal, k], True)
        column = f"column {found[signal, k] + 1} ({signal}{k + 1}_{_SUFFIX[signal]})"
        keep = ~np.isnan(values)
        free_force = signal == "F" and modes[k] == FREE
        if free_force or not keep.any():
            notes.append(f"{path}: {column} gives no curve: " + ("unit is free" if free_force else "empty"))
            continue
        curves.append(_curve(f"{path.name} unit {k + 1}", f"{path}, {column}", cfg, modes, d[keep], v[keep], k,
                             values[keep], signal))
    if not curves:
        raise DataError(f"{path}: no {_SIGNAL[signal]} curve (every {_SIGNAL[signal]} column is empty"
                        + (f" or of a free unit; modes {', '.join(modes)})" if signal == "F" else ")"))
    return curves, notes


def _curve(name: str, where: str, cfg: ArrayConfig, modes: Sequence[str], d: np.ndarray, v: np.ndarray,
           unit: int, values: np.ndarray, signal: str) -> MeasuredCurve:
    if len(values) < 3:
        raise DataError(f"{where}: {len(values)} measured sample(s); a curve needs at least 3")
    if not np.ptp(values) > 0:
        raise DataError(f"{where}: the measured {_SIGNAL[signal]} is constant, so its FIT is undefined")
    measured = {"force": values} if signal == "F" else {"capacitance": values}
    return MeasuredCurve(name, cfg, tuple(modes), d, v, unit, **measured)


# ----------------------------------------------------------------------- MCAP

def _held(times: np.ndarray, values: np.ndarray, at: np.ndarray, n: int) -> tuple[np.ndarray, np.ndarray]:
    """Commands held at times ``at`` (zero before the first message) and when they last changed."""
    previous = np.vstack([np.zeros((1, n)), values[:-1]])
    changed = times[np.any(values != previous, axis=1)]
    index = np.searchsorted(times, at, side="right") - 1
    held = np.where(index[:, None] >= 0, values[np.maximum(index, 0)], 0.0)
    last = np.searchsorted(changed, at, side="right") - 1
    return held, np.where(last >= 0, changed[np.maximum(last, 0)], -math.inf)


def read_bag(path: str | Path, config_path: str | None, modes: Sequence[str] | None, settle: float,
             topic_map: dict[str, str] | None = None, signal: str = "F") -> tuple[list[MeasuredCurve], list[str]]:
    """The force (``signal="F"``, one per driven unit) or capacitance (``"C"``, every unit) curves of a bag.

    Each recorded force (capacitance) message is paired with the displacement and voltage commands
    held at its log time; messages less than ``settle`` seconds after a command
    changed are dropped (the node answers at its next update).  Config and modes:
    ``config_path`` / ``modes`` if given, else the bag's metadata.

    Raises
    ------
    BagError
        Missing, not MCAP, truncated or damaged bag.
    DataError
        No force (capacitance) or displacement topic, messages not of the config's
        length, fewer than 3 settled samples, no unit whose measured signal varies.
        A unit whose signal is constant or NaN (a rig measuring only some units) is
        skipped with a note.
    """
    from ..bag.series import load_series

    bag = Bag(path)
    cfg, modes, notes = resolve_config(bag, config_path, modes)
    series, _ = load_series(bag, topic_map)
    n = cfg.n_units
    measured_kind = _SIGNAL[signal]
    for kind in ("displacement", measured_kind):
        if kind not in series:
            raise DataError(f"{path}: no {kind} topic (a topic ending with "
                            f"{'command/' if kind == 'displacement' else ''}{kind}); topics present:\n"
                            f"{bag.describe_topics()}")
    for s in series.values():
        if s.values.shape[1] != n:
            raise DataError(f"{path}: {s.topic} messages hold {s.values.shape[1]} values, but the config has {n} "
                            f"unit(s)")
    limit, commanded = cfg.scaled("max_displacement"), series["displacement"]
    beyond = np.flatnonzero(np.abs(commanded.values).max(axis=1) > limit)
    if beyond.size:
        i = beyond[0]
        raise DataError(f"{path}: {commanded.topic} at t = {commanded.time_s[i]:.6f} s commands "
                        f"{commanded.values[i].tolist()} m, beyond the config's max_displacement ({limit} m)")
    measured = series[measured_kind]
    d, d_changed = _held(series["displacement"].time_s, series["displacement"].values, measured.time_s, n)
    if "voltage" in series:
        v, v_changed = _held(series["voltage"].time_s, series["voltage"].values, measured.time_s, n)
    else:
        v, v_changed = np.zeros_like(d), np.full(len(d), -math.inf)
    keep = measured.time_s - np.maximum(d_changed, v_changed) >= settle
    notes.append(f"{path}: {keep.sum()} of {len(keep)} {measured_kind} message(s) are {settle} s or more after a "
                 f"command change (--settle)")
    curves = []
    for k in range(n):
        if modes[k] != DRIVEN and signal == "F":
            continue
        values, where = measured.values[keep, k], f"{path}, {measured.topic}[{k}] (--settle {settle})"
        if values.size >= 3 and not np.ptp(values) > 0:  # constant or NaN: this unit was not measured
            notes.append(f"{where}: the {measured_kind} of unit {k + 1} does not vary; no curve")
            continue
        curves.append(_curve(f"{Path(path).name} unit {k + 1}", where, cfg, modes, d[keep], v[keep], k, values,
                             signal))
    if not curves:
        raise DataError(f"{path}: no {measured_kind} curve: every unit is free or its {measured_kind} does not vary")
    return curves, notes


def load_curves(data: Sequence[str], config_path: str | None, modes: Sequence[str] | None, settle: float,
                topic_map: dict[str, str] | None = None, signal: str = "F") -> tuple[list[MeasuredCurve], list[str]]:
    """Curves of every DATA item (``FILE`` or ``FILE@CONFIG.yaml``) and notes for stderr.

    CSV files use ``FILE@CONFIG``, else ``config_path``, else the default config, and
    ``modes`` (default all driven); bags their recorded config and modes unless given.
    """
    curves, notes = [], []
    for item in data:
        path, own_config = item, None
        if not Path(item).exists() and "@" in item:
            path, _, own_config = item.rpartition("@")
        config = own_config or config_path
        if Path(path).is_dir() or Path(path).suffix.lower() == ".mcap":
            more, more_notes = read_bag(path, config, modes, settle, topic_map, signal)
        else:
            cfg = load_config(config)
            try:
                used = check_modes(modes if modes is not None else (DRIVEN,) * cfg.n_units, cfg.n_units)
            except ValueError as exc:
                raise ConfigError(f"--{exc}") from None
            more, more_notes = read_csv(path, cfg, used, signal)
            more_notes.insert(0, f"{path}: config {config or 'default'}, unit modes {', '.join(used)}")
        curves += more
        notes += more_notes
    return curves, notes



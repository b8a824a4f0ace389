"""ROS 2 message definitions as a rosbag2 MCAP file stores them: schema text and type hashes.

* :func:`message_definition`: the schema data of a type, encoding ``ros2msg``: the
  type's ``.msg`` text followed, for every nested non-builtin type (recursively, each
  once, dependencies of each type in sorted order as rosbag2 does), by ``"\\n"``, a
  line of 80 ``=``, a line ``MSG: pkg/Type`` and that type's ``.msg`` text;
* :func:`type_hash`: the channel's ``topic_type_hash``, the ``RIHS01_...`` string from
  ``share/<pkg>/msg/<Type>.json``;
* :func:`message_class`: the Python class of a type (imports ``<pkg>.msg``).

Both read the installed interface files, found through the ament index or else under
``sys.prefix``; no rclpy.  A missing ``.msg`` file raises the writer's
:class:`~.errors.RecordingError`.
"""

from __future__ import annotations

import functools
import importlib
import json
import sys
from pathlib import Path

from .errors import RecordingError

__all__ = ["message_class", "message_definition", "split_type_name", "type_hash"]

SEPARATOR = "=" * 80

_PRIMITIVES = frozenset({"bool", "byte", "char", "float32", "float64", "int8", "uint8", "int16", "uint16", "int32",
                         "uint32", "int64", "uint64", "string", "wstring"})


def split_type_name(type_name: str) -> tuple[str, str]:
    """``pkg/msg/Type`` or ``pkg/Type`` -> ``(pkg, Type)``."""
    parts = type_name.split("/")
    if len(parts) == 3 and parts[1] == "msg" and all(parts):
        return parts[0], parts[2]
    if len(parts) == 2 and all(parts):
        return parts[0], parts[1]
    raise ValueError(f"not a ROS 2 message type name (pkg/msg/Type): {type_name!r}")


def message_class(type_name: str) -> type:
    """The Python class of ``pkg/msg/Type`` (or ``pkg/Type``); ImportError if it is not installed."""
    package, name = split_type_name(type_name)
    try:
        return getattr(importlib.import_module(f"{package}.msg"), name)
    except (ImportError, AttributeError):
        raise ImportError(f"message type {type_name} is not installed (python package {package}.msg)") from None


def _share_dirs(package: str) -> list[Path]:
    """Where ``package``'s share directory may be: the ament index first, then ``sys.prefix``."""
    dirs = []
    try:
        from ament_index_python import get_package_share_directory
        dirs.append(Path(get_package_share_directory(package)))
    except Exception:  # noqa: BLE001 - AMENT_PREFIX_PATH unset (pip wheels), package not indexed, no ament
        pass
    dirs.append(Path(sys.prefix) / "share" / package)
    return dirs


def _interface_file(package: str, name: str, suffix: str) -> Path | None:
    for share in _share_dirs(package):
        path = share / "msg" / f"{name}{suffix}"
        if path.is_file():
            return path
    return None


@functools.lru_cache(maxsize=None)
def _msg_text(package: str, name: str) -> str:
    path = _interface_file(package, name, ".msg")
    if path is None:
        where = ", ".join(str(d / "msg") for d in _share_dirs(package))
        raise RecordingError(f"no message definition {package}/msg/{name}.msg found (looked in {where})")
    return path.read_text()


def _msg_dependencies(text: str, package: str) -> list[str]:
    """Non-builtin field types of a ``.msg`` text as sorted ``pkg/Type`` names.

    A field line is ``TYPE NAME [DEFAULT]`` or a constant ``TYPE NAME=VALUE``; ``TYPE`` may
    carry an array suffix (``[]``, ``[3]``, ``[<=3]``) or a string bound (``string<=8``).
    Unqualified types belong to ``package``.
    """
    deps = set()
    for line in text.splitlines():
        line = line.split("#", 1)[0].strip()
        if not line:
            continue
        base = line.split()[0].split("[", 1)[0].split("<=", 1)[0]
        if base in _PRIMITIVES:
            continue
        pkg, name = split_type_name(base) if "/" in base else (package, base)
        deps.add(f"{pkg}/{name}")
    return sorted(deps)


@functools.lru_cache(maxsize=None)
def message_definition(type_name: str) -> str:
    """The ``ros2msg`` schema text of a message type, with every nested type appended.

    Parameters
    ----------
    type_name
        ``pkg/msg/Type`` (or ``pkg/Type``).

    Returns
    -------
    str
        The type's ``.msg`` text; then, depth first, for each nested non-builtin type not
        yet included: ``"\\n"``, 80 ``=``, ``"\\nMSG: pkg/Type\\n"`` and its ``.msg`` text.

    Raises
    ------
    RecordingError
        A ``.msg`` file is not installed.
    """
    package, name = split_type_name(type_name)
    seen = {f"{package}/{name}"}

    def with_dependencies(pkg: str, typ: str) -> str:
        text = _msg_text(pkg, typ)
        out = [text]
        for dep in _msg_dependencies(text, pkg):
            if dep not in seen:
                seen.add(dep)
                out.append(f"\n{SEPARATOR}\nMSG: {dep}\n")
                out.append(with_dependencies(*dep.split("/")))
        return "".join(out)

    return with_dependencies(package, name)


@functools.lru_cache(maxsize=None)
def type_hash(type_name: str) -> str:
    """The type's ``RIHS01_...`` hash from ``share/<pkg>/msg/<Type>.json`` ("" if not installed).

    The json holds ``{"type_description_msg": ..., "type_hashes": [{"type_name":
    "pkg/msg/Type", "hash_string": "RIHS01_..."}, ...]}``: the entry of the type itself
    and one per referenced type.
    """
    package, name = split_type_name(type_name)
    path = _interface_file(package, name, ".json")
    if path is None:
        return ""
    try:
        hashes = json.loads(path.read_text()).get("type_hashes", [])
    except (OSError, ValueError, AttributeError):
        return ""
    full = f"{package}/msg/{name}"
    for entry in hashes:
        if isinstance(entry, dict) and entry.get("type_name") == full:
            return str(entry.get("hash_string", ""))
    return ""

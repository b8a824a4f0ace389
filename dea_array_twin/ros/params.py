"""ROS 2 parameters of the twin node: every :class:`ArrayConfig` field plus run-time ones.

Geometry, material and mesh fields are read-only after start (changing them means a
new mesh and a new model: restart the node).  Unit modes and the command limits can
change at run time.  The slip table (``slip_displacement``, ``slip_factor``) is a pair
of read-only DOUBLE_ARRAY parameters, unset when the table is empty (rclpy would type
an empty default as BYTE_ARRAY): ``-p slip_displacement:=[0.0,0.015] -p
slip_factor:=[1.0,0.95]``.
"""

from __future__ import annotations

import math
from typing import Any

from rcl_interfaces.msg import IntegerRange, ParameterDescriptor, ParameterType
from rclpy.parameter import Parameter

from ..model.config import ConfigError

#: Config fields that may change while the node runs (limits, checked per command).
RUNTIME_FIELDS = ("max_displacement", "breakdown_field")

_UNITS = {
    "length": "m", "width": "m", "frame_radius": "m", "electrode_diameter": "m", "spacing": "m",
    "indenter_radius": "m", "thickness": "m", "mesh_size": "m", "mesh_size_indenter": "m",
    "mesh_size_electrode": "m", "max_displacement": "m", "c10": "Pa", "c20": "Pa", "c30": "Pa",
    "breakdown_field": "V/m", "scale": "-", "epsr": "-", "prestretch": "-",
    "slip_displacement": "m", "slip_factor": "-",
    "experimental_hv_prestretch": "-", "experimental_hv_voltage": "V",
}
_RANGES = {"rows": (1, 64), "cols": (1, 64), "element_order": (1, 2)}


def config_descriptor(name: str, value: object) -> ParameterDescriptor:
    """Descriptor (description with unit, read-only flag, integer range) of a config field."""
    unit = _UNITS.get(name, "")
    doc = f"ArrayConfig.{name}" + (f" [{unit}]" if unit else "")
    desc = ParameterDescriptor(name=name, description=doc, read_only=name not in RUNTIME_FIELDS)
    if name in _RANGES:
        lo, hi = _RANGES[name]
        desc.integer_range = [IntegerRange(from_value=lo, to_value=hi, step=1)]
    if isinstance(value, list):
        desc.type = ParameterType.PARAMETER_DOUBLE_ARRAY
    elif isinstance(value, bool):
        desc.type = ParameterType.PARAMETER_BOOL
    elif isinstance(value, int):
        desc.type = ParameterType.PARAMETER_INTEGER
    elif isinstance(value, float):
        # Accept integers too ("-p prestretch:=2"): ArrayConfig.from_dict converts.
        desc.dynamic_typing = True
    else:
        desc.type = ParameterType.PARAMETER_STRING
    return desc


def declared_default(value: object) -> Any:
    """The default to declare a config field's parameter with (``declare_parameter``'s value).

    ``value`` is from :meth:`.ArrayConfig.to_dict`.  A table is a list of float (a
    DOUBLE_ARRAY); an empty one becomes the type
    ``Parameter.Type.DOUBLE_ARRAY`` alone, which declares the parameter unset:
    rclpy infers ``[]`` as BYTE_ARRAY, and a YAML or ``-p`` list of doubles would
    then be rejected as the wrong type.  Unset reads back as None.
    """
    if isinstance(value, list) and not value:
        return Parameter.Type.DOUBLE_ARRAY
    return value


def declare_number(node: Any, name: str, default: float, text: str, minimum: float = 0.0) -> float:
    """Declare a read-only numeric parameter of ``node`` and return it as a finite float >= ``minimum``.

    Integers are accepted too (``-p rate:=20``): the parameter is dynamically typed.

    Raises
    ------
    ConfigError
        The value is not a number, not finite or below ``minimum``; the message names it.
    """
    value = node.declare_parameter(name, default, ParameterDescriptor(
        description=text, read_only=True, dynamic_typing=True)).value
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not (minimum <= value < math.inf):
        raise ConfigError(f"{name}: must be a number >= {minimum:g}, got {value!r}")
    return float(value)

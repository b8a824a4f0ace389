"""ROS 2 parameters of the twin node: every :class:`ArrayConfig` field plus run-time ones.

Geometry, material and mesh fields are read-only after start (changing them means a
new mesh and a new model: restart the node).  Unit modes and the command limits can
change at run time.

Every parameter holds a value of a fixed type from the start, because rclpy's
``get_parameters`` service (what ``ros2 param dump``, rqt and Foxglove call) answers
nothing at all for a request that names one unset parameter:

* a float field is a DOUBLE even when given as an integer (``-p prestretch:=2``) or
  as a number in a string (``1e8``, which YAML 1.1 reads as text), as in a config file;
* the slip table (``slip_displacement``, ``slip_factor``) is a DOUBLE_ARRAY, empty
  when there is no table (rclpy would type a plain ``[]`` default as BYTE_ARRAY):
  ``-p slip_displacement:=[0.0,0.015] -p slip_factor:=[1.0,0.95]``.

The run-time doubles are dynamically typed so that the node's own check, which names
the parameter and the allowed range, judges every value (a BOOL is refused by name,
not by rclpy's bare type message); :func:`coerce_doubles` turns integers and numeric
text into doubles before that check, so a parameter never changes its type.

Per-unit fields are flattened to one array entry per unit (:func:`config_parameters`):
``unit_modes`` (STRING_ARRAY, the node declares it dynamically typed and checks it
itself), ``mass``, ``damping`` (DOUBLE_ARRAY), ``contact`` (BOOL_ARRAY), and the ``bias``
list as ``bias.type`` (``none``, ``linear``, ``constant``, ``table``, ``sum``),
``bias.stiffness`` [N/m], ``bias.free_position`` [m] and ``bias.force`` [N] (the fields of
a linear or constant bias; 0 where a unit's law has no such field).  In a params file
these are nested, ``bias: {type: [linear, none, linear], stiffness: [40.0, 0.0, 40.0],
...}``.  A ``table`` or ``sum`` bias has no flat form: it comes only from the config
file (``config_file``), and ``bias.type`` names it for that unit.
"""

from __future__ import annotations

import math
from typing import Any, Iterable

from rcl_interfaces.msg import IntegerRange, ParameterDescriptor, ParameterType
from rclpy.node import Node
from rclpy.parameter import Parameter

from ..model.bias import ConstantBias, LinearBias, NoBias
from ..model.config import UNIT_FIELDS, ArrayConfig, ConfigError

#: Config fields that may change while the node runs (limits, checked per command).
RUNTIME_FIELDS = ("max_displacement", "breakdown_field")
#: Parameters of the ``bias`` field and the attribute of the linear or constant law each holds.
BIAS_PARAMETERS = {"bias.type": None, "bias.stiffness": ("linear", "stiffness"),
                   "bias.free_position": ("linear", "free_position"), "bias.force": ("constant", "force_N")}

_UNITS = {
    "length": "m", "width": "m", "frame_radius": "m", "electrode_diameter": "m", "spacing": "m",
    "indenter_radius": "m", "thickness": "m", "mesh_size": "m", "mesh_size_indenter": "m",
    "mesh_size_electrode": "m", "max_displacement": "m", "c10": "Pa", "c20": "Pa", "c30": "Pa",
    "breakdown_field": "V/m", "scale": "-", "epsr": "-", "prestretch": "-",
    "slip_displacement": "m", "slip_factor": "-",
    "experimental_hv_prestretch": "-", "experimental_hv_voltage": "V",
    "mass": "kg per unit", "damping": "N s/m per unit",
    "bias.stiffness": "N/m per unit", "bias.free_position": "m per unit", "bias.force": "N per unit",
}
_TEXT = {"contact": "per unit: the indenter only pushes (lifts off instead of pulling)",
         "bias.type": "per unit bias law: none, linear, constant (table and sum from config_file only)"}
_RANGES = {"rows": (1, 64), "cols": (1, 64), "element_order": (1, 2)}


def config_descriptor(name: str, value: object) -> ParameterDescriptor:
    """Descriptor (description with unit, read-only flag, type, integer range) of a config field."""
    unit = _UNITS.get(name, "")
    doc = f"ArrayConfig.{name}" + (f" [{unit}]" if unit else "") + (f": {_TEXT[name]}" if name in _TEXT else "")
    desc = ParameterDescriptor(name=name, description=doc, read_only=name not in RUNTIME_FIELDS)
    if name in _RANGES:
        lo, hi = _RANGES[name]
        desc.integer_range = [IntegerRange(from_value=lo, to_value=hi, step=1)]
    if isinstance(value, list) and value and isinstance(value[0], str):
        desc.type = ParameterType.PARAMETER_STRING_ARRAY
    elif isinstance(value, list) and value and isinstance(value[0], bool):
        desc.type = ParameterType.PARAMETER_BOOL_ARRAY
    elif isinstance(value, list):
        desc.type = ParameterType.PARAMETER_DOUBLE_ARRAY
    elif isinstance(value, bool):
        desc.type = ParameterType.PARAMETER_BOOL
    elif isinstance(value, int):
        desc.type = ParameterType.PARAMETER_INTEGER
    elif isinstance(value, float):
        desc.type = ParameterType.PARAMETER_DOUBLE
    else:
        desc.type = ParameterType.PARAMETER_STRING
    return desc


def as_double(name: str, value: Any) -> float:
    """``value`` as a float the way the config loader takes it (int, float or numeric text), else ConfigError."""
    if isinstance(value, bool) or not isinstance(value, (int, float, str)):
        raise ConfigError(f"{name}: expected a number, got {value!r}")
    try:
        return float(value)
    except ValueError:
        raise ConfigError(f"{name}: expected a number, got {value!r}") from None


def declare_typed(node: Node, name: str, default: Any, descriptor: ParameterDescriptor) -> Any:
    """Declare a parameter that is set from the start and keeps the type of ``descriptor``; return its value.

    ``descriptor.type`` says the type: a DOUBLE accepts an integer or numeric-text
    override and stores it as a double; a DOUBLE_ARRAY without a value (an empty
    table) is set to an empty double array.  A run-time double (not read-only)
    stays dynamically typed (see the module docstring).

    Raises
    ------
    ConfigError
        A DOUBLE parameter was given something that is not a number; the message names it.
    """
    final = ParameterDescriptor()
    final.name, final.description, final.read_only = name, descriptor.description, descriptor.read_only
    final.type, final.integer_range = descriptor.type, descriptor.integer_range
    final.floating_point_range = descriptor.floating_point_range
    double = descriptor.type == ParameterType.PARAMETER_DOUBLE
    table = descriptor.type == ParameterType.PARAMETER_DOUBLE_ARRAY
    first = ParameterDescriptor(name=name, description=descriptor.description)  # writable until set below
    if double:
        first.dynamic_typing = True
        value = node.declare_parameter(name, default, first).value
    elif table and not default:
        value = node.declare_parameter(name, Parameter.Type.DOUBLE_ARRAY, first).value
    else:
        first.type, first.integer_range = descriptor.type, descriptor.integer_range
        value = node.declare_parameter(name, default, first).value
    if double and not isinstance(value, float):
        value = as_double(name, value)
        node.set_parameters([Parameter(name, Parameter.Type.DOUBLE, value)])
    elif table and value is None:
        value = []
        node.set_parameters([Parameter(name, Parameter.Type.DOUBLE_ARRAY, value)])
    if double and not final.read_only:
        final.dynamic_typing = True
        final.type = ParameterType.PARAMETER_NOT_SET
    node.set_descriptor(name, final)
    return value


def declare_number(node: Node, name: str, default: float, text: str, minimum: float = 0.0) -> float:
    """Declare a read-only DOUBLE parameter of ``node`` and return it, a finite float >= ``minimum``.

    Integers are accepted too (``-p rate:=20``) and stored as doubles.

    Raises
    ------
    ConfigError
        The value is not a number, not finite or below ``minimum``; the message names it.
    """
    value = declare_typed(node, name, float(default), ParameterDescriptor(
        description=text, read_only=True, type=ParameterType.PARAMETER_DOUBLE))
    if not minimum <= value < math.inf:
        raise ConfigError(f"{name}: must be a number >= {minimum:g}, got {value!r}")
    return value


def coerce_doubles(params: Iterable[Parameter], names: Iterable[str]) -> list[Parameter]:
    """A pre-set callback's work: integers and numeric text for the double parameters ``names`` become doubles.

    Anything else is passed on unchanged, for the on-set check to refuse by name.
    """
    names = set(names)
    out = []
    for p in params:
        if p.name in names and p.type_ in (Parameter.Type.INTEGER, Parameter.Type.STRING):
            try:
                p = Parameter(p.name, Parameter.Type.DOUBLE, as_double(p.name, p.value))
            except ConfigError:
                pass
        out.append(p)
    return out


def config_parameters(cfg: ArrayConfig) -> dict[str, Any]:
    """The node's parameters of ``cfg``: every field, per-unit fields flattened to one entry per unit."""
    out = {}
    for name, value in cfg.to_dict().items():
        if name == "bias":
            laws = cfg.per_unit("bias")
            out["bias.type"] = [law.kind for law in laws]
            for key, field in BIAS_PARAMETERS.items():
                if field is not None:
                    out[key] = [float(getattr(law, field[1])) if law.kind == field[0] else 0.0 for law in laws]
        elif name in UNIT_FIELDS:
            out[name] = list(cfg.per_unit(name))
        else:
            out[name] = value
    return out


def config_from_parameters(values: dict[str, Any], base: ArrayConfig) -> ArrayConfig:
    """The config of the node's parameter ``values`` (:func:`config_parameters`' names).

    ``base`` is the config file's: a unit whose ``bias.type`` is ``table`` or ``sum``
    takes its law from there.

    Raises
    ------
    ConfigError
        A bad value, or a table/sum bias the config file does not give; names the parameter.
    """
    values = dict(values)
    kinds = values.pop("bias.type")
    columns = {key: values.pop(key) for key, field in BIAS_PARAMETERS.items() if field is not None}
    n = base.n_units
    for key, column in [("bias.type", kinds)] + list(columns.items()):
        if len(column) != n:
            raise ConfigError(f"{key}: needs one entry per unit ({n}), got {len(column)}")
    file_laws = base.per_unit("bias")
    laws = []
    for k, kind in enumerate(kinds):
        if kind == "none":
            laws.append(NoBias())
        elif kind == "linear":
            laws.append(LinearBias(columns["bias.stiffness"][k], columns["bias.free_position"][k]))
        elif kind == "constant":
            laws.append(ConstantBias(columns["bias.force"][k]))
        elif kind in ("table", "sum") and file_laws[k].kind == kind:
            laws.append(file_laws[k])
        elif kind in ("table", "sum"):
            raise ConfigError(f"bias.type[{k}]: a {kind} bias comes only from the config file (config_file), "
                              f"which gives unit {k + 1} a {file_laws[k].kind} bias")
        else:
            raise ConfigError(f"bias.type[{k}]: must be one of none, linear, constant, table, sum; got {kind!r}")
    values["bias"] = [law.to_dict() for law in laws]
    return ArrayConfig.from_dict(values)

"""Turn :class:`~tactile_deploy.runtime.ros.messages.RosMessage` data into real message objects.

* :class:`RosbagsCodec`: rosbags message classes and CDR bytes, the ROS 2 wire format, without
  ROS (the definitions of ROS 2 Humble, wire-compatible with Jazzy and Kilted: only a constant
  of visualization_msgs/Marker differs), and the ``ros2msg`` definition text that MCAP files
  carry for each type;
* :func:`fill_rclpy` fills rclpy message objects (used by :mod:`.node`).

Field values: numbers and strings as they are; nested messages as dicts; arrays of numbers as
numpy arrays; arrays of messages as a list of dicts or as an (n, k) numpy array whose columns are
the element's fields in their order (e.g. Point: x, y, z), which is how the mesh builders pass
thousands of points cheaply. Fields left out take ROS defaults (0, "", empty).
"""

from __future__ import annotations

import array
import functools

import numpy as np

#: rosbags store of the message definitions written.
ROS_DISTRO = "humble"

_NUMPY_TYPES = {
    "bool": np.bool_, "byte": np.uint8, "char": np.uint8, "int8": np.int8, "uint8": np.uint8,
    "int16": np.int16, "uint16": np.uint16, "int32": np.int32, "uint32": np.uint32,
    "int64": np.int64, "uint64": np.uint64, "float32": np.float32, "float64": np.float64,
}


class RosbagsCodec:
    """rosbags message objects, CDR serialisation and message definitions of ROS 2 types."""

    def __init__(self) -> None:
        from rosbags.typesys import Stores, get_typestore

        self.typestore = get_typestore(Stores.ROS2_HUMBLE)

    @functools.lru_cache(maxsize=64)  # noqa: B019 - one codec per recording, few types
    def msgdef(self, type_name: str) -> str:
        """The ``ros2msg`` definition text of ``type_name`` with its dependencies (MCAP schema)."""
        text, _digest = self.typestore.generate_msgdef(type_name, ros_version=2)
        return text

    def build(self, type_name: str, fields: dict):
        """The rosbags message object of ``type_name`` holding ``fields`` (module docstring)."""
        return self._build(type_name, fields or {})

    def serialize(self, message) -> bytes:
        """CDR bytes (little-endian) of a :class:`RosMessage`."""
        obj = self.build(message.type, message.fields)
        return bytes(self.typestore.serialize_cdr(obj, message.type))

    def _build(self, type_name: str, fields: dict):
        from rosbags.typesys.store import Nodetype

        _consts, defs = self.typestore.fielddefs[type_name]
        known = {name for name, _ in defs}
        unknown = set(fields) - known
        if unknown:
            raise ValueError(f"{type_name} has no field(s) {sorted(unknown)}; it has {sorted(known)}")
        cls = self.typestore.types[type_name]
        kwargs = {}
        for name, (kind, spec) in defs:
            value = fields.get(name)
            if kind == Nodetype.BASE:
                kwargs[name] = _base(spec[0], value)
            elif kind == Nodetype.NAME:
                kwargs[name] = self._build(spec, value or {})
            else:  # ARRAY (fixed length) or SEQUENCE
                (ekind, espec), length = spec
                if ekind == Nodetype.BASE:
                    dtype = _NUMPY_TYPES.get(espec[0])
                    if dtype is None:       # arrays of strings
                        kwargs[name] = list(value or [""] * (length or 0))
                    else:
                        arr = np.zeros(length or 0, dtype) if value is None else np.asarray(value, dtype)
                        kwargs[name] = np.ascontiguousarray(arr.reshape(-1))
                else:
                    kwargs[name] = self._sequence(espec, value, length or 0)
        return cls(**kwargs)

    def _sequence(self, type_name: str, value, length: int) -> list:
        if value is None:
            return [self._build(type_name, {}) for _ in range(length)]
        if isinstance(value, np.ndarray):
            cls = self.typestore.types[type_name]
            _c, defs = self.typestore.fielddefs[type_name]
            if value.ndim != 2 or value.shape[1] != len(defs):
                raise ValueError(f"an array of {type_name} must be (n, {len(defs)}) "
                                 f"({', '.join(n for n, _ in defs)}), got {value.shape}")
            return [cls(*row) for row in value.tolist()]
        return [self._build(type_name, v) for v in value]


def _base(ros_type: str, value):
    if ros_type == "string":
        return "" if value is None else str(value)
    if ros_type == "bool":
        return bool(value) if value is not None else False
    if ros_type in ("float32", "float64"):
        return 0.0 if value is None else float(value)
    return 0 if value is None else int(value)


def fill_rclpy(msg, fields: dict, get_message):
    """Fill the rclpy message ``msg`` with ``fields`` (module docstring), recursively.

    get_message : ``"pkg/msg/Type" -> class`` (``rosidl_runtime_py.utilities.get_message``).
    Uses only the rclpy message API: ``get_fields_and_field_types()`` (field -> type string such
    as ``"std_msgs/Header"``, ``"sequence<geometry_msgs/Point>"``, ``"sequence<uint8>"``) and
    attribute assignment.
    """
    types = msg.get_fields_and_field_types()
    for name, value in fields.items():
        if name not in types:
            raise ValueError(f"{type(msg).__name__} has no field {name!r}; it has {sorted(types)}")
        t = types[name]
        element = _element_type(t)
        if element is None:                          # a single value
            if "/" in t:
                fill_rclpy(getattr(msg, name), value, get_message)
            else:
                setattr(msg, name, value)
        elif "/" in element:                         # an array of messages
            cls = get_message(_full_name(element))
            setattr(msg, name, [_rclpy_element(cls, v, get_message) for v in
                                (value.tolist() if isinstance(value, np.ndarray) else value)])
        else:                                        # an array of numbers
            arr = np.asarray(value).reshape(-1)
            code = _ARRAY_CODES.get(element)
            if t.startswith("sequence") and code is not None:   # rclpy keeps these in array.array
                setattr(msg, name, array.array(code, arr.astype(_NUMPY_TYPES[element]).tobytes()))
            else:
                setattr(msg, name, arr.tolist())
    return msg


#: array.array type codes of the number types rclpy stores sequences of in array.array.
_ARRAY_CODES = {"int8": "b", "uint8": "B", "int16": "h", "uint16": "H", "int32": "i",
                "uint32": "I", "int64": "q", "uint64": "Q", "float32": "f", "float64": "d"}


def _rclpy_element(cls, value, get_message):
    obj = cls()
    if isinstance(value, dict):
        return fill_rclpy(obj, value, get_message)
    for fname, v in zip(obj.get_fields_and_field_types(), value):   # a row of an (n, k) array
        setattr(obj, fname, v)
    return obj


def _element_type(t: str) -> str | None:
    if t.startswith("sequence<"):
        return t[len("sequence<"):].split(",")[0].rstrip(">")
    if t.endswith("]") and "[" in t:
        return t[: t.index("[")]
    return None


def _full_name(short: str) -> str:
    pkg, _, name = short.partition("/")
    return short if name.startswith("msg/") else f"{pkg}/msg/{name}"

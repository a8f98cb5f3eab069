"""Sparkplug B payloads and topics: encode what compd publishes, decode (distrustfully) what a host sends.

The schema is Eclipse Tahu's `sparkplug_b.proto` (package `org.eclipse.tahu.protobuf`, proto2),
declared here as a descriptor at import time: no protoc, no generated code, and a private
descriptor pool, so another copy of the schema loaded elsewhere in the process cannot clash.
Field numbers and types are Tahu's, so the bytes are what Ignition, Tahu and any other
Sparkplug host read. Declared: Payload, Metric, MetaData, PropertySet, PropertySetList and
PropertyValue. DataSet (17), Template (18) and the extension values are not declared: a metric
carrying one decodes with a SparkplugError (compd neither sends nor expects them).

Value conventions (Sparkplug 3.0; checked against Tahu's Python and Java libraries):

- Int8/Int16/Int32 travel in `int_value` (uint32), Int64 in `long_value` (uint64), as two's
  complement of the type's own width (Int8 −1 → 255, as Tahu's Python sends). Decoding also
  takes a negative sign-extended to 32 bits (Int8 −1 → 4294967295, as Java's `setIntValue`
  sends); any other value out of the type's range is an error, not silently wrapped.
- UInt32 is sent in `int_value` (the spec; Tahu since 2022); decoding also takes `long_value`,
  where Ignition and older Tahu put it.
- DateTime is milliseconds since the Unix epoch in `long_value`.
- A metric whose datatype is left out (0, Unknown: the spec lets DATA and CMD messages omit
  it) decodes to the raw value of whichever value field it carries (an int as sent, unsigned);
  the receiver knows the type from the birth certificate.

Aliases (Sparkplug 3.0, payloads chapter): an edge node that uses them gives every metric of its
NBIRTH and DBIRTHs a name and an alias, each alias unique across the node and all its devices
(`AliasTable`), except `Node Control/Rebirth`, which keeps its name only; its NDATA, DDATA, NCMD
and DCMD then carry the alias and no name (`encode(..., aliases=..., names=False)`). A host maps
them back with the births it holds (`AliasResolver`).
"""

from __future__ import annotations

import math
import numbers
import struct
import uuid as uuid_mod
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from enum import IntEnum
from typing import Any

import numpy as np
from google.protobuf import descriptor_pb2, descriptor_pool, message, message_factory

NAMESPACE = "spBv1.0"

NODE_TYPES = frozenset({"NBIRTH", "NDEATH", "NDATA", "NCMD"})
DEVICE_TYPES = frozenset({"DBIRTH", "DDEATH", "DDATA", "DCMD"})
MESSAGE_TYPES = NODE_TYPES | DEVICE_TYPES | {"STATE"}
BIRTH_TYPES = frozenset({"NBIRTH", "DBIRTH"})
# Sparkplug 3.0 forbids an alias on the NBIRTH's `Node Control/Rebirth`: a host writes it by
# name, whatever aliases the node uses
UNALIASED = frozenset({"Node Control/Rebirth"})


class DataType(IntEnum):
    """Sparkplug B data types, with Tahu's numbers (a metric's `datatype`, a property's `type`)."""

    Unknown = 0
    Int8 = 1
    Int16 = 2
    Int32 = 3
    Int64 = 4
    UInt8 = 5
    UInt16 = 6
    UInt32 = 7
    UInt64 = 8
    Float = 9
    Double = 10
    Boolean = 11
    String = 12
    DateTime = 13
    Text = 14
    UUID = 15
    DataSet = 16
    Bytes = 17
    File = 18
    Template = 19
    # property value types only
    PropertySet = 20
    PropertySetList = 21
    # Sparkplug 3.0 arrays (packed in bytes_value): known, not supported here
    Int8Array = 22
    Int16Array = 23
    Int32Array = 24
    Int64Array = 25
    UInt8Array = 26
    UInt16Array = 27
    UInt32Array = 28
    UInt64Array = 29
    FloatArray = 30
    DoubleArray = 31
    BooleanArray = 32
    StringArray = 33
    DateTimeArray = 34


class SparkplugError(ValueError):
    """A payload or topic that is not what it claims (one line)."""

    def __init__(self, message: str) -> None:
        super().__init__(str(message).replace("\r", " ").replace("\n", " "))


@dataclass(frozen=True)
class MetricDef:
    """A metric as the birth certificate announces it: name, datatype and (births only) its unit."""

    name: str
    datatype: DataType
    unit: str | None = None  # sent as the property "engUnit" (String) when encoding with properties

    def __post_init__(self) -> None:
        if not isinstance(self.name, str) or not self.name:
            raise SparkplugError(f"metric name {self.name!r}: a non-empty string is needed")
        try:
            object.__setattr__(self, "datatype", DataType(self.datatype))
        except ValueError:
            raise SparkplugError(f"metric {self.name!r}: no Sparkplug datatype {self.datatype!r}") from None
        if self.unit is not None and not isinstance(self.unit, str):
            raise SparkplugError(f"metric {self.name!r}: unit {self.unit!r} is not a string")


@dataclass
class Metric:
    """A decoded metric. `value` is None when is_null; signed integers come back signed."""

    name: str | None
    alias: int | None
    timestamp_ms: int | None
    datatype: DataType
    value: Any
    is_historical: bool = False
    is_null: bool = False
    properties: dict[str, Any] = field(default_factory=dict)


@dataclass
class Payload:
    """A decoded payload: absent optional fields are None."""

    timestamp_ms: int | None
    seq: int | None
    metrics: list[Metric]
    uuid: str | None = None
    body: bytes | None = None


# --- the schema -------------------------------------------------------------------------------

_PACKAGE = "org.eclipse.tahu.protobuf"
_F = descriptor_pb2.FieldDescriptorProto


def _field(
    msg: descriptor_pb2.DescriptorProto,
    name: str,
    number: int,
    kind: int,
    *,
    repeated: bool = False,
    type_name: str | None = None,
    oneof: int | None = None,
) -> None:
    f = msg.field.add(
        name=name,
        number=number,
        type=kind,
        label=_F.LABEL_REPEATED if repeated else _F.LABEL_OPTIONAL,
    )
    if type_name is not None:
        f.type_name = f".{_PACKAGE}.Payload.{type_name}"
    if oneof is not None:
        f.oneof_index = oneof


def _schema() -> descriptor_pb2.FileDescriptorProto:
    """The part of Tahu's sparkplug_b.proto compd uses, with Tahu's field numbers and types."""
    fp = descriptor_pb2.FileDescriptorProto(name="compd/plant/sparkplug_b.proto", package=_PACKAGE, syntax="proto2")
    payload = fp.message_type.add(name="Payload")

    pv = payload.nested_type.add(name="PropertyValue")
    pv.oneof_decl.add(name="value")
    _field(pv, "type", 1, _F.TYPE_UINT32)
    _field(pv, "is_null", 2, _F.TYPE_BOOL)
    _field(pv, "int_value", 3, _F.TYPE_UINT32, oneof=0)
    _field(pv, "long_value", 4, _F.TYPE_UINT64, oneof=0)
    _field(pv, "float_value", 5, _F.TYPE_FLOAT, oneof=0)
    _field(pv, "double_value", 6, _F.TYPE_DOUBLE, oneof=0)
    _field(pv, "boolean_value", 7, _F.TYPE_BOOL, oneof=0)
    _field(pv, "string_value", 8, _F.TYPE_STRING, oneof=0)
    _field(pv, "propertyset_value", 9, _F.TYPE_MESSAGE, type_name="PropertySet", oneof=0)
    _field(pv, "propertysets_value", 10, _F.TYPE_MESSAGE, type_name="PropertySetList", oneof=0)

    ps = payload.nested_type.add(name="PropertySet")
    _field(ps, "keys", 1, _F.TYPE_STRING, repeated=True)
    _field(ps, "values", 2, _F.TYPE_MESSAGE, repeated=True, type_name="PropertyValue")

    psl = payload.nested_type.add(name="PropertySetList")
    _field(psl, "propertyset", 1, _F.TYPE_MESSAGE, repeated=True, type_name="PropertySet")

    md = payload.nested_type.add(name="MetaData")
    _field(md, "is_multi_part", 1, _F.TYPE_BOOL)
    _field(md, "content_type", 2, _F.TYPE_STRING)
    _field(md, "size", 3, _F.TYPE_UINT64)
    _field(md, "seq", 4, _F.TYPE_UINT64)
    _field(md, "file_name", 5, _F.TYPE_STRING)
    _field(md, "file_type", 6, _F.TYPE_STRING)
    _field(md, "md5", 7, _F.TYPE_STRING)
    _field(md, "description", 8, _F.TYPE_STRING)

    m = payload.nested_type.add(name="Metric")
    m.oneof_decl.add(name="value")
    _field(m, "name", 1, _F.TYPE_STRING)
    _field(m, "alias", 2, _F.TYPE_UINT64)
    _field(m, "timestamp", 3, _F.TYPE_UINT64)
    _field(m, "datatype", 4, _F.TYPE_UINT32)
    _field(m, "is_historical", 5, _F.TYPE_BOOL)
    _field(m, "is_transient", 6, _F.TYPE_BOOL)
    _field(m, "is_null", 7, _F.TYPE_BOOL)
    _field(m, "metadata", 8, _F.TYPE_MESSAGE, type_name="MetaData")
    _field(m, "properties", 9, _F.TYPE_MESSAGE, type_name="PropertySet")
    _field(m, "int_value", 10, _F.TYPE_UINT32, oneof=0)
    _field(m, "long_value", 11, _F.TYPE_UINT64, oneof=0)
    _field(m, "float_value", 12, _F.TYPE_FLOAT, oneof=0)
    _field(m, "double_value", 13, _F.TYPE_DOUBLE, oneof=0)
    _field(m, "boolean_value", 14, _F.TYPE_BOOL, oneof=0)
    _field(m, "string_value", 15, _F.TYPE_STRING, oneof=0)
    _field(m, "bytes_value", 16, _F.TYPE_BYTES, oneof=0)

    _field(payload, "timestamp", 1, _F.TYPE_UINT64)
    _field(payload, "metrics", 2, _F.TYPE_MESSAGE, repeated=True, type_name="Metric")
    _field(payload, "seq", 3, _F.TYPE_UINT64)
    _field(payload, "uuid", 4, _F.TYPE_STRING)
    _field(payload, "body", 5, _F.TYPE_BYTES)
    return fp


_pool = descriptor_pool.DescriptorPool()
_pool.Add(_schema())
# the message class (what protoc would generate as sparkplug_b_pb2.Payload), for tests and tools
PayloadMessage: Any = message_factory.GetMessageClass(_pool.FindMessageTypeByName(f"{_PACKAGE}.Payload"))

# --- values -----------------------------------------------------------------------------------

_U32 = 1 << 32
_U64 = 1 << 64
_FLOAT32_MAX = struct.unpack("<f", b"\xff\xff\x7f\x7f")[0]

# integer types: (bits, signed, value field)
_INTS: dict[DataType, tuple[int, bool, str]] = {
    DataType.Int8: (8, True, "int_value"),
    DataType.Int16: (16, True, "int_value"),
    DataType.Int32: (32, True, "int_value"),
    DataType.Int64: (64, True, "long_value"),
    DataType.UInt8: (8, False, "int_value"),
    DataType.UInt16: (16, False, "int_value"),
    DataType.UInt32: (32, False, "int_value"),
    DataType.UInt64: (64, False, "long_value"),
    DataType.DateTime: (64, False, "long_value"),
}
_STRINGS = frozenset({DataType.String, DataType.Text, DataType.UUID})
_BYTES = frozenset({DataType.Bytes, DataType.File})
_ENCODABLE = frozenset(_INTS) | {DataType.Float, DataType.Double, DataType.Boolean} | _STRINGS | _BYTES


def _show(text: object, limit: int = 60) -> str:
    """A name from the network as it can stand in a one-line message: quoted, escaped, cut short."""
    shown = repr(text)
    return shown if len(shown) <= limit else shown[: limit - 3] + "..."


def _is_int(value: Any) -> bool:
    return isinstance(value, numbers.Integral) and not isinstance(value, bool | np.bool_)


def _set_value(msg: Any, datatype: DataType, value: Any, where: str) -> None:
    """Put a Python value into the value field its datatype travels in (a Metric or a PropertyValue)."""
    if datatype in _INTS:
        bits, signed, fieldname = _INTS[datatype]
        if not _is_int(value):
            raise SparkplugError(f"{where}: {datatype.name} needs an integer, not {type(value).__name__}")
        value = int(value)
        low, high = (-(1 << (bits - 1)), (1 << (bits - 1)) - 1) if signed else (0, (1 << bits) - 1)
        if not low <= value <= high:
            raise SparkplugError(f"{where}: {value} is out of range for {datatype.name}")
        setattr(msg, fieldname, value % (1 << bits))  # two's complement of the type's width
    elif datatype in (DataType.Float, DataType.Double):
        if not isinstance(value, numbers.Real) or isinstance(value, bool | np.bool_):
            raise SparkplugError(f"{where}: {datatype.name} needs a number, not {type(value).__name__}")
        try:
            number = float(value)
        except (OverflowError, ValueError) as e:
            raise SparkplugError(f"{where}: {value!r} is not a {datatype.name}: {e}") from None
        if datatype is DataType.Float:
            if math.isfinite(number) and abs(number) > _FLOAT32_MAX:
                raise SparkplugError(f"{where}: {number!r} is out of range for Float (32 bits)")
            msg.float_value = number
        else:
            msg.double_value = number
    elif datatype is DataType.Boolean:
        if not isinstance(value, bool | np.bool_):
            raise SparkplugError(f"{where}: Boolean needs a bool, not {type(value).__name__}")
        msg.boolean_value = bool(value)
    elif datatype in _STRINGS:
        if datatype is DataType.UUID and isinstance(value, uuid_mod.UUID):
            value = str(value)
        if not isinstance(value, str):
            raise SparkplugError(f"{where}: {datatype.name} needs a str, not {type(value).__name__}")
        if datatype is DataType.UUID:
            try:
                uuid_mod.UUID(value)
            except ValueError:
                raise SparkplugError(f"{where}: {_show(value)} is not a UUID") from None
        try:
            value.encode("utf-8")
        except UnicodeEncodeError:
            raise SparkplugError(f"{where}: the text is not valid Unicode (a lone surrogate)") from None
        msg.string_value = value
    elif datatype in _BYTES and hasattr(msg, "bytes_value"):
        if not isinstance(value, bytes | bytearray | memoryview):
            raise SparkplugError(f"{where}: {datatype.name} needs bytes, not {type(value).__name__}")
        msg.bytes_value = bytes(value)
    else:
        raise SparkplugError(f"{where}: datatype {datatype.name} is not supported")


def encode(
    values: Sequence[tuple[MetricDef, Any]],
    *,
    timestamp_ms: int,
    seq: int | None,
    historical: bool = False,
    with_properties: bool = False,
    metric_timestamp_ms: int | None = None,
    aliases: Mapping[str, int] | None = None,
    names: bool = True,
) -> bytes:
    """One Sparkplug B payload: each (definition, value) a metric, with its datatype.

    A value of None is sent as is_null (no value field). `seq` is the payload's sequence
    number (0–255), None for a message without one (NDEATH). `historical` marks every metric
    is_historical (samples sent late from the store-and-forward buffer); `with_properties`
    adds the engUnit property (births); `metric_timestamp_ms` stamps every metric.

    `aliases` (name → alias) gives each metric it names its alias; with `names` (the default)
    the name goes too (a birth), without (a DATA or CMD message by alias) every metric must have
    an alias and carries no name, or SparkplugError.

    Values must fit their datatype, or SparkplugError: integers (Python or numpy, never bool)
    within the type's range; Float/Double take any real number but not a bool (a flag sent as
    a number is a wiring mistake: use Boolean), NaN and ±inf are sent as they are, and a
    finite value beyond float32's range is refused for Float rather than sent as inf; Boolean
    takes only bool; String/Text take str, UUID a uuid.UUID or its text; Bytes/File take
    bytes-like; DateTime takes int ms since the epoch. DataSet, Template and arrays are not
    supported.
    """
    msg = PayloadMessage()
    try:
        msg.timestamp = _check_u64(timestamp_ms, "timestamp_ms")
        if seq is not None:
            if not _is_int(seq) or not 0 <= seq <= 255:
                raise SparkplugError(f"seq {seq!r} is not 0..255")
            msg.seq = int(seq)
        stamp = None if metric_timestamp_ms is None else _check_u64(metric_timestamp_ms, "metric_timestamp_ms")
        if not names and aliases is None:
            raise SparkplugError("a message without names needs aliases")
        for definition, value in values:
            if not isinstance(definition, MetricDef):
                raise SparkplugError(f"{definition!r} is not a MetricDef")
            where = f"metric {_show(definition.name)}"
            m = msg.metrics.add()
            alias = None if aliases is None else aliases.get(definition.name)
            if alias is not None:
                m.alias = _check_u64(alias, f"{where}: alias")
            elif not names:
                raise SparkplugError(f"{where} has no alias: a message by alias cannot carry it")
            if names:
                m.name = definition.name
            m.datatype = int(definition.datatype)
            if stamp is not None:
                m.timestamp = stamp
            if historical:
                m.is_historical = True
            if with_properties and definition.unit is not None:
                m.properties.keys.append("engUnit")
                unit = m.properties.values.add()
                unit.type = int(DataType.String)
                _set_value(unit, DataType.String, definition.unit, f"{where} engUnit")
            if value is None:
                if definition.datatype not in _ENCODABLE:
                    raise SparkplugError(f"{where}: datatype {definition.datatype.name} is not supported")
                m.is_null = True
            else:
                _set_value(m, definition.datatype, value, where)
        return msg.SerializeToString()
    except SparkplugError:
        raise
    except (TypeError, ValueError) as e:  # protobuf's own refusal, should a check above miss one
        raise SparkplugError(f"cannot encode: {e}") from None


def _check_u64(value: Any, what: str) -> int:
    if not _is_int(value) or not 0 <= value < _U64:
        raise SparkplugError(f"{what} {value!r} is not an integer 0..2^64-1")
    return int(value)


def _text(value: Any, where: str) -> str:
    """A string field as parsed: proto2 does not check UTF-8, so invalid bytes arrive as bytes."""
    if not isinstance(value, str):
        raise SparkplugError(f"{where} is not valid UTF-8")
    return value


def _int_from_wire(raw: int, datatype: DataType, where: str) -> int:
    bits, signed, _ = _INTS[datatype]
    if bits < 32 and raw >= 1 << bits:
        if signed and raw >= _U32 - (1 << (bits - 1)):  # sign-extended to 32 bits (Java)
            return raw - _U32
        raise SparkplugError(f"{where}: {raw} is out of range for {datatype.name}")
    if signed and raw >= 1 << (bits - 1):
        return raw - (1 << bits)
    return raw


_RAW_FIELDS = ("int_value", "long_value", "float_value", "double_value", "boolean_value", "string_value", "bytes_value")


def _get_value(msg: Any, datatype: DataType, where: str) -> Any:
    """The Python value of a Metric's or PropertyValue's value field, checked against its datatype."""
    present = msg.WhichOneof("value")
    if datatype is DataType.Unknown:
        if present not in _RAW_FIELDS:
            raise SparkplugError(f"{where}: no datatype and no value")
        value = getattr(msg, present)
        return _text(value, where) if present == "string_value" else value
    if datatype in _INTS:
        _, _, fieldname = _INTS[datatype]
        if datatype is DataType.UInt32 and present == "long_value":  # Ignition, older Tahu
            if msg.long_value >= _U32:
                raise SparkplugError(f"{where}: {msg.long_value} is out of range for UInt32")
            return msg.long_value
        expected = fieldname
    elif datatype is DataType.Float:
        expected = "float_value"
    elif datatype is DataType.Double:
        expected = "double_value"
    elif datatype is DataType.Boolean:
        expected = "boolean_value"
    elif datatype in _STRINGS:
        expected = "string_value"
    elif datatype in _BYTES and msg.DESCRIPTOR.name == "Metric":
        expected = "bytes_value"
    elif datatype is DataType.PropertySet and msg.DESCRIPTOR.name == "PropertyValue":
        if present != "propertyset_value":
            raise SparkplugError(f"{where}: PropertySet without a property set")
        return _properties(msg.propertyset_value, where)
    elif datatype is DataType.PropertySetList and msg.DESCRIPTOR.name == "PropertyValue":
        if present != "propertysets_value":
            raise SparkplugError(f"{where}: PropertySetList without a list of property sets")
        return [_properties(s, f"{where}[{i}]") for i, s in enumerate(msg.propertysets_value.propertyset)]
    else:
        raise SparkplugError(f"{where}: datatype {datatype.name} is not supported")
    if present != expected:
        got = "no value" if present is None else present
        raise SparkplugError(f"{where}: {datatype.name} in {got}, expected {expected}")
    value = getattr(msg, expected)
    if datatype in _INTS:
        return _int_from_wire(value, datatype, where)
    if datatype in _STRINGS:
        return _text(value, where)
    return value


def _datatype(number: int, where: str) -> DataType:
    try:
        return DataType(number)
    except ValueError:
        raise SparkplugError(f"{where}: unknown datatype {number}") from None


def _properties(ps: Any, where: str) -> dict[str, Any]:
    keys = list(ps.keys)
    if len(keys) != len(ps.values):
        raise SparkplugError(f"{where}: {len(keys)} property keys for {len(ps.values)} values")
    out: dict[str, Any] = {}
    for key, pv in zip(keys, ps.values, strict=True):
        key = _text(key, f"{where}: a property key")
        there = f"{where} property {_show(key)}"
        if key in out:
            raise SparkplugError(f"{there}: given twice")
        kind = _datatype(pv.type, there)
        out[key] = None if pv.is_null else _get_value(pv, kind, there)
    return out


def decode(data: bytes, *, max_metrics: int = 10_000) -> Payload:
    """A Sparkplug B payload from the network, checked: nothing in it is trusted.

    Anything malformed — not protobuf, truncated, an unknown datatype, a value in the wrong
    field for its datatype or out of its range, more than `max_metrics` metrics, a string
    that is not UTF-8 — raises SparkplugError with one line, never another exception.
    """
    try:
        return _decode(data, max_metrics)
    except SparkplugError:
        raise
    except MemoryError:
        raise
    except Exception as e:  # the contract: one error type, whatever the bytes did
        raise SparkplugError(f"malformed Sparkplug B payload: {type(e).__name__}: {e}") from None


def _decode(data: bytes, max_metrics: int) -> Payload:
    if not isinstance(data, bytes | bytearray | memoryview):
        raise SparkplugError(f"a payload is bytes, not {type(data).__name__}")
    try:
        msg = PayloadMessage.FromString(bytes(data))
    except message.DecodeError as e:
        raise SparkplugError(f"not a Sparkplug B payload: {e}") from None
    if len(msg.metrics) > max_metrics:
        raise SparkplugError(f"{len(msg.metrics)} metrics, more than the {max_metrics} accepted")
    metrics = []
    for i, m in enumerate(msg.metrics):
        name = _text(m.name, f"metric #{i}: its name") if m.HasField("name") else None
        where = f"metric {_show(name)}" if name is not None else f"metric #{i}"
        datatype = _datatype(m.datatype, where)
        metrics.append(
            Metric(
                name=name,
                alias=m.alias if m.HasField("alias") else None,
                timestamp_ms=m.timestamp if m.HasField("timestamp") else None,
                datatype=datatype,
                value=None if m.is_null else _get_value(m, datatype, where),
                is_historical=m.is_historical,
                is_null=m.is_null,
                properties=_properties(m.properties, where) if m.HasField("properties") else {},
            )
        )
    return Payload(
        timestamp_ms=msg.timestamp if msg.HasField("timestamp") else None,
        seq=msg.seq if msg.HasField("seq") else None,
        metrics=metrics,
        uuid=_text(msg.uuid, "the payload's uuid") if msg.HasField("uuid") else None,
        body=msg.body if msg.HasField("body") else None,
    )


# --- aliases ----------------------------------------------------------------------------------


class AliasTable:
    """The aliases of one edge node: one number per metric of the node (device None) or of one of
    its devices, unique across the node and all its devices (Sparkplug 3.0). Given from `first` on
    in the order the metrics are first declared, never taken back or given to another metric while
    the table lives: a rebirth, or a set of metrics that changed, keeps every alias it had.
    `Node Control/Rebirth` gets none (UNALIASED)."""

    def __init__(self, first: int = 1) -> None:
        if not _is_int(first) or not 0 <= first < _U64:
            raise SparkplugError(f"first alias {first!r} is not 0..2^64-1")
        self._alias: dict[tuple[str | None, str], int] = {}
        self._key: dict[int, tuple[str | None, str]] = {}
        self._next = int(first)

    def declare(self, device: str | None, names: Iterable[str]) -> dict[str, int]:
        """name → alias of these metrics of the node (`device` None) or of a device, the new ones
        numbered now; an UNALIASED name is left out (it goes by name)."""
        out: dict[str, int] = {}
        for name in names:
            if name in UNALIASED:
                continue
            key = (device, name)
            alias = self._alias.get(key)
            if alias is None:
                if self._next >= _U64:
                    raise SparkplugError("no alias left (2^64 given)")
                alias = self._next
                self._next += 1
                self._alias[key] = alias
                self._key[alias] = key
            out[name] = alias
        return out

    def name(self, device: str | None, alias: int) -> str | None:
        """The metric of the node (device None) or of that device with this alias, or None."""
        key = self._key.get(alias) if _is_int(alias) else None
        return key[1] if key is not None and key[0] == device else None

    def __len__(self) -> int:
        return len(self._alias)


class AliasResolver:
    """What a Sparkplug host keeps of the births: per edge node the alias → (name, datatype) of its
    NBIRTH and of each device's DBIRTH. `resolve` gives the metrics of a DATA or CMD message that
    came by alias their names back (and their datatype, where the message left it out). A new
    NBIRTH or an NDEATH forgets the node's births, a DDEATH its device's."""

    def __init__(self) -> None:
        self._births: dict[tuple[str, str, str | None], dict[int, tuple[str, DataType]]] = {}

    def resolve(self, topic_name: str, payload: Payload) -> list[int]:
        """Fill in the names (in place) of `payload`'s metrics that came by alias, from the birth of
        the node or device the topic names; the aliases that birth did not declare (left nameless).
        A topic that is not Sparkplug B raises SparkplugError."""
        group, kind, node, device = parse_topic(topic_name)
        if kind == "STATE":
            return []
        if kind in ("NBIRTH", "NDEATH"):
            for key in [k for k in self._births if k[0] == group and k[1] == node]:
                del self._births[key]
        if kind == "DDEATH":
            self._births.pop((group, node, device), None)
        if kind in BIRTH_TYPES:
            self._births[(group, node, device)] = {
                m.alias: (m.name, m.datatype) for m in payload.metrics if m.alias is not None and m.name is not None
            }
        if kind in BIRTH_TYPES or kind.endswith("DEATH"):
            return []
        born = self._births.get((group, node, device), {})
        unknown: list[int] = []
        for i, m in enumerate(payload.metrics):
            if m.name is not None or m.alias is None:
                continue
            hit = born.get(m.alias)
            if hit is None:
                unknown.append(m.alias)
                continue
            m.name = hit[0]
            if m.datatype is DataType.Unknown and hit[1] is not DataType.Unknown:
                m.value = _typed(m.value, hit[1], f"metric #{i} (alias {m.alias}, {_show(hit[0])})")
                m.datatype = hit[1]
        return unknown


def _typed(raw: Any, datatype: DataType, where: str) -> Any:
    """The raw value of a metric sent without its datatype, as the datatype its birth declared
    (SparkplugError when it does not fit)."""
    if raw is None:
        return None
    if datatype in _INTS and _is_int(raw):
        return _int_from_wire(int(raw), datatype, where)
    if datatype in (DataType.Float, DataType.Double) and isinstance(raw, float):
        return raw
    if datatype is DataType.Boolean and isinstance(raw, bool):
        return raw
    if datatype in _STRINGS and isinstance(raw, str):
        return raw
    if datatype in _BYTES and isinstance(raw, bytes):
        return raw
    raise SparkplugError(f"{where}: a {type(raw).__name__} is not a {datatype.name}")


# --- topics -----------------------------------------------------------------------------------


def _check_id(value: Any, what: str) -> str:
    if not isinstance(value, str) or not value:
        raise SparkplugError(f"{what} {value!r}: a non-empty string is needed")
    bad = sorted({c for c in value if c in "/+#"})
    if bad:
        raise SparkplugError(f"{what} {_show(value)} contains {' '.join(bad)}")
    try:
        value.encode("utf-8")
    except UnicodeEncodeError:
        raise SparkplugError(f"{what} {_show(value)} is not valid Unicode") from None
    return value


def topic(group_id: str, message_type: str, edge_node_id: str, device_id: str | None = None) -> str:
    """The Sparkplug B topic: `spBv1.0/<group>/<type>/<edge node>[/<device>]`.

    NBIRTH, NDEATH, NDATA and NCMD take no device id; DBIRTH, DDEATH, DDATA and DCMD need
    one. STATE (Sparkplug 3.0: `spBv1.0/STATE/<host id>`) has no group: pass group_id ""
    and the host application's id as edge_node_id.
    """
    if message_type == "STATE":
        if group_id != "" or device_id is not None:
            raise SparkplugError("a STATE topic is spBv1.0/STATE/<host id>: no group or device id")
        return f"{NAMESPACE}/STATE/{_check_id(edge_node_id, 'host id')}"
    if message_type not in MESSAGE_TYPES:
        raise SparkplugError(f"message type {_show(message_type)} is not one of {' '.join(sorted(MESSAGE_TYPES))}")
    parts = [NAMESPACE, _check_id(group_id, "group id"), message_type, _check_id(edge_node_id, "edge node id")]
    if message_type in DEVICE_TYPES:
        if device_id is None:
            raise SparkplugError(f"{message_type} needs a device id")
        parts.append(_check_id(device_id, "device id"))
    elif device_id is not None:
        raise SparkplugError(f"{message_type} takes no device id")
    return "/".join(parts)


def parse_topic(topic: str) -> tuple[str, str, str, str | None]:
    """(group_id, message_type, edge_node_id, device_id or None) of a Sparkplug B topic.

    A STATE topic parses as ("", "STATE", host_id, None). Anything else — another namespace,
    too few or too many levels, an unknown message type, a device id where none belongs (or
    missing), an empty level, a wildcard — raises SparkplugError.
    """
    if not isinstance(topic, str):
        raise SparkplugError(f"a topic is a str, not {type(topic).__name__}")
    parts = topic.split("/")
    if parts[0] != NAMESPACE:
        raise SparkplugError(f"topic {_show(topic)} is not in the {NAMESPACE} namespace")
    if len(parts) == 3 and parts[1] == "STATE":
        return "", "STATE", _check_id(parts[2], f"topic {_show(topic)}: host id"), None
    if len(parts) not in (4, 5):
        raise SparkplugError(f"topic {_show(topic)} has {len(parts)} levels, not 4 or 5")
    where = f"topic {_show(topic)}:"
    group_id = _check_id(parts[1], f"{where} group id")
    message_type = parts[2]
    edge_node_id = _check_id(parts[3], f"{where} edge node id")
    if message_type in NODE_TYPES:
        if len(parts) == 5:
            raise SparkplugError(f"{where} {message_type} takes no device id")
        return group_id, message_type, edge_node_id, None
    if message_type in DEVICE_TYPES:
        if len(parts) == 4:
            raise SparkplugError(f"{where} {message_type} needs a device id")
        return group_id, message_type, edge_node_id, _check_id(parts[4], f"{where} device id")
    raise SparkplugError(f"{where} unknown message type {_show(message_type)}")

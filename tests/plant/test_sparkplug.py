"""Sparkplug B payloads and topics: round trips, Tahu's wire bytes, and decoding whatever the network sends."""

from __future__ import annotations

import math
import struct
import uuid

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from compd.plant.sparkplug import (
    NAMESPACE,
    UNALIASED,
    AliasResolver,
    AliasTable,
    DataType,
    MetricDef,
    Payload,
    PayloadMessage,
    SparkplugError,
    decode,
    encode,
    parse_topic,
    topic,
)

D = DataType


def f32(x: float) -> float:
    """x as a float32 holds it."""
    return struct.unpack("<f", struct.pack("<f", x))[0]


def one(datatype: DataType, value: object, **kw: object) -> object:
    """The value of one metric after encode → decode."""
    data = encode([(MetricDef("m", datatype), value)], timestamp_ms=1, seq=0, **kw)
    (m,) = decode(data).metrics
    assert m.datatype is datatype and m.name == "m"
    return m.value


# --- round trips ------------------------------------------------------------------------------

ROUND_TRIP = [
    (D.Int8, [-128, -87, -1, 0, 1, 127]),
    (D.Int16, [-32768, -1, 0, 32767]),
    (D.Int32, [-(2**31), -1, 0, 2**31 - 1]),
    (D.Int64, [-(2**63), -1, 0, 2**63 - 1]),
    (D.UInt8, [0, 255]),
    (D.UInt16, [0, 65535]),
    (D.UInt32, [0, 2**32 - 1]),
    (D.UInt64, [0, 2**64 - 1]),
    (D.Float, [0.0, 1.5, -2.25, 3.4028234663852886e38]),
    (D.Double, [0.0, -0.0, 0.1, 1e300, 5e-324, -1.7976931348623157e308]),
    (D.Boolean, [True, False]),
    (D.String, ["", "µm", "20.5 °C", "x\ny", "ünïcødé ✓ 🛠"]),
    (D.Text, ["a longer text, µm and °C"]),
    (D.UUID, ["1b4e28ba-2fa1-11d2-883f-0016d3cca427"]),
    (D.DateTime, [0, 1_700_000_000_123]),
    (D.Bytes, [b"", b"\x00\xff\x80"]),
    (D.File, [b"G90 G54\n"]),
]


@pytest.mark.parametrize(("datatype", "values"), ROUND_TRIP, ids=[d.name for d, _ in ROUND_TRIP])
def test_every_scalar_datatype_round_trips(datatype, values):
    for value in values:
        got = one(datatype, value)
        assert got == value and type(got) is type(value), (datatype, value, got)
        if isinstance(value, float):
            assert math.copysign(1.0, got) == math.copysign(1.0, value)  # -0.0 stays -0.0


def test_float_is_rounded_to_32_bits():
    assert one(D.Float, 0.1) == f32(0.1)
    assert one(D.Float, np.float32(20.25)) == 20.25
    assert one(D.Float, 3) == 3.0  # an int is a number


@pytest.mark.parametrize("datatype", [D.Float, D.Double])
def test_nan_and_infinities_are_sent_as_such(datatype):
    assert math.isnan(one(datatype, float("nan")))
    assert one(datatype, math.inf) == math.inf
    assert one(datatype, -math.inf) == -math.inf


def test_numpy_scalars_are_taken():
    assert one(D.Int16, np.int16(-5)) == -5
    assert one(D.UInt64, np.uint64(2**64 - 1)) == 2**64 - 1
    assert one(D.Double, np.float64(2.5)) == 2.5
    assert one(D.Boolean, np.bool_(True)) is True
    assert one(D.UUID, uuid.UUID(int=1)) == "00000000-0000-0000-0000-000000000001"


@pytest.mark.parametrize("datatype", [d for d, _ in ROUND_TRIP])
def test_none_is_sent_as_null(datatype):
    data = encode([(MetricDef("m", datatype), None)], timestamp_ms=5, seq=1)
    (m,) = decode(data).metrics
    assert m.is_null and m.value is None and m.datatype is datatype
    raw = PayloadMessage.FromString(data).metrics[0]
    assert raw.WhichOneof("value") is None  # no value field at all, as the spec wants


def test_birth_carries_eng_units_and_data_does_not():
    defs = [
        (MetricDef("x/correction_um", D.Double, "µm"), -1.25),
        (MetricDef("T_xi", D.Float, "°C"), 21.5),
        (MetricDef("state", D.String), "normal"),
    ]
    birth = decode(encode(defs, timestamp_ms=10, seq=0, with_properties=True))
    assert [m.properties for m in birth.metrics] == [{"engUnit": "µm"}, {"engUnit": "°C"}, {}]
    data = decode(encode(defs, timestamp_ms=10, seq=1))
    assert [m.properties for m in data.metrics] == [{}, {}, {}]
    raw = PayloadMessage.FromString(encode(defs, timestamp_ms=10, seq=0, with_properties=True))
    assert raw.metrics[0].properties.values[0].type == 12  # String


def test_payload_fields_and_flags():
    data = encode(
        [(MetricDef("a", D.Int32), -3), (MetricDef("b", D.Boolean), True)],
        timestamp_ms=1_700_000_000_000,
        seq=255,
        historical=True,
        metric_timestamp_ms=1_699_999_999_000,
    )
    p = decode(data)
    assert isinstance(p, Payload)
    assert (p.timestamp_ms, p.seq, p.uuid, p.body) == (1_700_000_000_000, 255, None, None)
    assert all(m.is_historical and m.timestamp_ms == 1_699_999_999_000 and m.alias is None for m in p.metrics)
    assert [m.value for m in p.metrics] == [-3, True]
    death = decode(encode([(MetricDef("bdSeq", D.UInt64), 7)], timestamp_ms=1, seq=None))
    assert death.seq is None and death.metrics[0].timestamp_ms is None and not death.metrics[0].is_historical


# --- the exact bytes --------------------------------------------------------------------------


def varint(n: int) -> bytes:
    out = bytearray()
    while True:
        low, n = n & 0x7F, n >> 7
        out.append(low | (0x80 if n else 0))
        if not n:
            return bytes(out)


def key(number: int, wire: int) -> bytes:
    """A field's tag: number << 3 | wire type (0 varint, 1 64-bit, 2 length-delimited, 5 32-bit)."""
    return varint(number << 3 | wire)


def vint(number: int, n: int) -> bytes:
    return key(number, 0) + varint(n)


def vlen(number: int, data: bytes) -> bytes:
    return key(number, 2) + varint(len(data)) + data


def test_encode_gives_tahus_wire_bytes():
    defs = [
        (MetricDef("i8", D.Int8), -2),
        (MetricDef("i64", D.Int64), -1),
        (MetricDef("f", D.Float), 1.5),
        (MetricDef("d", D.Double, "µm"), 2.5),
        (MetricDef("b", D.Boolean), True),
        (MetricDef("s", D.String), "°C"),
        (MetricDef("raw", D.Bytes), b"\x01\x02"),
        (MetricDef("u32", D.UInt32), 7),
        (MetricDef("gone", D.Double), None),
    ]
    got = encode(defs, timestamp_ms=1000, seq=5, historical=True, with_properties=True, metric_timestamp_ms=999)

    def metric(name: str, datatype: int, value: bytes, extra: bytes = b"") -> bytes:
        # name=1, timestamp=3, datatype=4, is_historical=5, (is_null=7, properties=9), value=10..16
        return vlen(2, vlen(1, name.encode()) + vint(3, 999) + vint(4, datatype) + vint(5, 1) + extra + value)

    eng_unit = vlen(9, vlen(1, b"engUnit") + vlen(2, vint(1, 12) + vlen(8, "µm".encode())))
    expected = (
        vint(1, 1000)  # Payload.timestamp = 1
        + metric("i8", 1, vint(10, 254))  # int_value = 10, two's complement 8 bits
        + metric("i64", 4, vint(11, 2**64 - 1))  # long_value = 11
        + metric("f", 9, key(12, 5) + struct.pack("<f", 1.5))  # float_value = 12
        + metric("d", 10, key(13, 1) + struct.pack("<d", 2.5), eng_unit)  # double_value = 13
        + metric("b", 11, vint(14, 1))  # boolean_value = 14
        + metric("s", 12, vlen(15, "°C".encode()))  # string_value = 15
        + metric("raw", 17, vlen(16, b"\x01\x02"))  # bytes_value = 16
        + metric("u32", 7, vint(10, 7))  # UInt32 in int_value
        + metric("gone", 10, b"", vint(7, 1))  # is_null = 7
        + vint(3, 5)  # Payload.seq = 3
    )
    assert got == expected
    # spot checks of the helpers themselves against numbers from the protobuf documentation
    assert varint(150) == b"\x96\x01" and key(16, 2) == b"\x82\x01"


def test_uuid_and_body_field_numbers():
    msg = PayloadMessage.FromString(vint(1, 1) + vlen(4, b"abc") + vlen(5, b"\x00\x01"))
    p = decode(msg.SerializeToString())
    assert (p.uuid, p.body, p.seq) == ("abc", b"\x00\x01", None)


# --- what other implementations send ------------------------------------------------------------


def raw_metric(datatype: int, field_bytes: bytes, name: str = "m") -> bytes:
    return vint(1, 1) + vlen(2, vlen(1, name.encode()) + vint(4, datatype) + field_bytes)


@pytest.mark.parametrize(
    ("datatype", "raw", "value"),
    [
        (D.Int8, 0xFF, -1),  # Tahu Python: the type's own width
        (D.Int8, 0xFFFFFFFF, -1),  # Java: sign-extended to 32 bits
        (D.Int8, 0xFFFFFF80, -128),
        (D.Int16, 0xFFA9, -87),
        (D.Int16, 0xFFFFFFA9, -87),
        (D.Int32, 0x80000000, -(2**31)),
        (D.UInt16, 0xFFFF, 65535),
    ],
)
def test_signed_integers_from_either_convention(datatype, raw, value):
    assert decode(raw_metric(datatype, vint(10, raw))).metrics[0].value == value


def test_uint32_also_from_long_value_as_ignition_sends_it():
    assert decode(raw_metric(D.UInt32, vint(11, 4_000_000_000))).metrics[0].value == 4_000_000_000
    with pytest.raises(SparkplugError, match="out of range"):
        decode(raw_metric(D.UInt32, vint(11, 2**32)))


def test_int32_written_as_negative_int64_varint():
    # a writer that put a negative int32 as a 10-byte varint: protobuf keeps the low 32 bits
    assert decode(raw_metric(D.Int32, vint(10, 2**64 - 5))).metrics[0].value == -5


def test_metric_without_datatype_gives_the_raw_value():
    # the spec lets NCMD/DCMD leave the datatype out; the birth tells the receiver what it is
    m = decode(vint(1, 1) + vlen(2, vlen(1, b"Node Control/Rebirth") + vint(14, 1))).metrics[0]
    assert (m.datatype, m.value) == (D.Unknown, True)
    m = decode(vint(1, 1) + vlen(2, vint(2, 12) + vint(10, 0xFFFFFFFF))).metrics[0]
    assert (m.name, m.alias, m.value) == (None, 12, 0xFFFFFFFF)


def test_properties_of_every_kind_decode():
    pv_set = vlen(9, vlen(1, b"inner") + vlen(2, vint(1, 3) + vint(3, 0xFFFFFFFE)))
    props = (
        vlen(1, b"engUnit")
        + vlen(1, b"max")
        + vlen(1, b"none")
        + vlen(1, b"nested")
        + vlen(2, vint(1, 12) + vlen(8, "°C".encode()))
        + vlen(2, vint(1, 10) + key(6, 1) + struct.pack("<d", 80.0))
        + vlen(2, vint(1, 3) + vint(2, 1))
        + vlen(2, vint(1, 20) + pv_set)
    )
    m = decode(raw_metric(D.Double, key(13, 1) + struct.pack("<d", 1.0) + vlen(9, props))).metrics[0]
    assert m.properties == {"engUnit": "°C", "max": 80.0, "none": None, "nested": {"inner": -2}}


# --- decoding refuses -----------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("data", "match"),
    [
        (b"\xff\xff\xff", "not a Sparkplug B payload"),
        (vlen(2, b"\x0a\x05ab"), "not a Sparkplug B payload"),  # truncated
        (raw_metric(99, vint(10, 1)), "unknown datatype 99"),
        (raw_metric(D.Double, vint(10, 1)), "Double in int_value, expected double_value"),
        (raw_metric(D.Int8, vint(10, 300)), "out of range for Int8"),
        (raw_metric(D.UInt8, vint(10, 0xFFFFFFFF)), "out of range for UInt8"),
        (raw_metric(D.Int16, vint(10, 0x10000)), "out of range for Int16"),
        (raw_metric(D.Int64, vint(10, 1)), "expected long_value"),
        (raw_metric(D.Boolean, b""), "Boolean in no value"),
        (raw_metric(D.DataSet, vlen(17, b"")), "DataSet is not supported"),
        (raw_metric(D.Int8Array, vlen(16, b"\x01")), "Int8Array is not supported"),
        (raw_metric(D.String, vlen(15, b"\xff\xfe")), "not valid UTF-8"),
        (vint(1, 1) + vlen(2, vlen(1, b"\xc3\x28") + vint(4, 11) + vint(14, 1)), "not valid UTF-8"),
        (vlen(4, b"\x80"), "uuid is not valid UTF-8"),
        (raw_metric(D.Double, key(13, 1) + struct.pack("<d", 1.0) + vlen(9, vlen(1, b"k"))), "1 property keys for 0"),
        (
            raw_metric(
                D.Double,
                key(13, 1) + struct.pack("<d", 1.0) + vlen(9, vlen(1, b"k") + vlen(2, vint(1, 77) + vint(3, 1))),
            ),
            "unknown datatype 77",
        ),
        (vint(1, 1) + vlen(2, b""), "no datatype and no value"),
    ],
)
def test_malformed_payloads_raise_one_line(data, match):
    with pytest.raises(SparkplugError, match=match) as e:
        decode(data)
    assert "\n" not in str(e.value)


def test_max_metrics():
    data = encode([(MetricDef(f"m{i}", D.Boolean), True) for i in range(11)], timestamp_ms=1, seq=0)
    assert len(decode(data, max_metrics=11).metrics) == 11
    with pytest.raises(SparkplugError, match="11 metrics, more than the 10"):
        decode(data, max_metrics=10)


def test_a_name_with_a_newline_stays_one_line():
    data = raw_metric(99, vint(10, 1), name="evil\nname")
    with pytest.raises(SparkplugError) as e:
        decode(data)
    assert "\n" not in str(e.value) and "evil\\nname" in str(e.value)


@settings(max_examples=400, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(st.binary(max_size=300))
def test_arbitrary_bytes_decode_or_raise_sparkplug_error(data):
    try:
        assert isinstance(decode(data), Payload)
    except SparkplugError as e:
        assert "\n" not in str(e)


_VALUE_FIELDS = st.sampled_from(
    [
        ("int_value", st.integers(0, 2**32 - 1)),
        ("long_value", st.integers(0, 2**64 - 1)),
        ("float_value", st.floats(width=32)),
        ("double_value", st.floats()),
        ("boolean_value", st.booleans()),
        ("string_value", st.text(max_size=5)),
        ("bytes_value", st.binary(max_size=5)),
        (None, st.none()),
    ]
)


@st.composite
def wild_payloads(draw) -> bytes:
    """Well-formed protobuf with any datatype, value field, flags and properties: the semantic checks' turn."""
    msg = PayloadMessage()
    if draw(st.booleans()):
        msg.seq = draw(st.integers(0, 2**64 - 1))
    for _ in range(draw(st.integers(0, 4))):
        m = msg.metrics.add()
        if draw(st.booleans()):
            m.name = draw(st.text(max_size=4))
        if draw(st.booleans()):
            m.datatype = draw(st.integers(0, 40))
        m.is_null = draw(st.booleans())
        fieldname, values = draw(_VALUE_FIELDS)
        if fieldname:
            setattr(m, fieldname, draw(values))
        for _ in range(draw(st.integers(0, 2))):
            m.properties.keys.append(draw(st.sampled_from(["a", "b", "engUnit"])))
        for _ in range(draw(st.integers(0, 2))):
            pv = m.properties.values.add()
            pv.type = draw(st.integers(0, 25))
            pfield, pvalues = draw(_VALUE_FIELDS)
            if pfield and pfield != "bytes_value":
                setattr(pv, pfield, draw(pvalues))
    data = msg.SerializeToString()
    if draw(st.booleans()) and data:  # and now and then a damaged copy
        i = draw(st.integers(0, len(data) - 1))
        data = data[:i] + bytes([draw(st.integers(0, 255))]) + data[i + 1 :]
    return data


@settings(max_examples=400, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(wild_payloads())
def test_wild_payloads_decode_or_raise_sparkplug_error(data):
    try:
        assert isinstance(decode(data), Payload)
    except SparkplugError as e:
        assert "\n" not in str(e)


# --- encoding refuses -----------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("datatype", "value", "match"),
    [
        (D.Int8, 128, "out of range for Int8"),
        (D.Int8, -129, "out of range for Int8"),
        (D.UInt8, -1, "out of range for UInt8"),
        (D.UInt32, 2**32, "out of range for UInt32"),
        (D.UInt64, 2**64, "out of range for UInt64"),
        (D.Int64, 2**63, "out of range for Int64"),
        (D.Int32, True, "needs an integer, not bool"),
        (D.Int32, 1.0, "needs an integer, not float"),
        (D.Double, True, "needs a number, not bool"),
        (D.Double, "1.0", "needs a number, not str"),
        (D.Double, 10**400, "is not a Double"),
        (D.Float, 1e39, "out of range for Float"),
        (D.Boolean, 1, "needs a bool"),
        (D.String, b"x", "needs a str"),
        (D.String, "\ud800", "lone surrogate"),
        (D.UUID, "not-a-uuid", "is not a UUID"),
        (D.Bytes, "text", "needs bytes"),
        (D.DataSet, object(), "DataSet is not supported"),
        (D.Template, None, "Template is not supported"),
    ],
)
def test_values_that_do_not_fit_are_refused(datatype, value, match):
    with pytest.raises(SparkplugError, match=match):
        encode([(MetricDef("m", datatype), value)], timestamp_ms=1, seq=0)


def test_bad_definitions_and_header_values_are_refused():
    with pytest.raises(SparkplugError, match="no Sparkplug datatype 99"):
        MetricDef("m", 99)
    with pytest.raises(SparkplugError, match="non-empty"):
        MetricDef("", D.Double)
    assert MetricDef("m", 10).datatype is D.Double
    ok = [(MetricDef("m", D.Double), 1.0)]
    with pytest.raises(SparkplugError, match="seq 256"):
        encode(ok, timestamp_ms=1, seq=256)
    with pytest.raises(SparkplugError, match="timestamp_ms -1"):
        encode(ok, timestamp_ms=-1, seq=0)


def test_datatype_numbers_are_tahus():
    expected = {
        "Unknown": 0,
        "Int8": 1,
        "Int16": 2,
        "Int32": 3,
        "Int64": 4,
        "UInt8": 5,
        "UInt16": 6,
        "UInt32": 7,
        "UInt64": 8,
        "Float": 9,
        "Double": 10,
        "Boolean": 11,
        "String": 12,
        "DateTime": 13,
        "Text": 14,
        "UUID": 15,
        "DataSet": 16,
        "Bytes": 17,
        "File": 18,
        "Template": 19,
        "PropertySet": 20,
        "PropertySetList": 21,
        "Int8Array": 22,
        "DateTimeArray": 34,
    }
    assert {name: DataType[name].value for name in expected} == expected


# --- topics ---------------------------------------------------------------------------------------


def test_topics():
    assert topic("plant", "NBIRTH", "edge1") == "spBv1.0/plant/NBIRTH/edge1"
    assert topic("plant", "DDATA", "edge1", "m1") == "spBv1.0/plant/DDATA/edge1/m1"
    assert topic("", "STATE", "scada") == "spBv1.0/STATE/scada"
    for t in ["spBv1.0/plant/NDEATH/edge1", "spBv1.0/hall 2/DCMD/edge-1/Maschine µ"]:
        assert topic(*parse_topic(t)) == t
    assert parse_topic("spBv1.0/plant/DBIRTH/e/d") == ("plant", "DBIRTH", "e", "d")
    assert parse_topic("spBv1.0/plant/NCMD/e") == ("plant", "NCMD", "e", None)
    assert parse_topic("spBv1.0/STATE/scada") == ("", "STATE", "scada", None)
    assert NAMESPACE == "spBv1.0"


@pytest.mark.parametrize(
    "bad",
    [
        "spAv1.0/plant/NDATA/e",  # another namespace
        "plant/NDATA/e",
        "spBv1.0/plant/NDATA",  # too few levels
        "spBv1.0/plant",
        "spBv1.0",
        "spBv1.0/plant/DDATA/e/d/x",  # too many
        "spBv1.0/plant/NDATA/e/d",  # a device on a node message
        "spBv1.0/plant/DDATA/e",  # no device on a device message
        "spBv1.0/plant/XDATA/e",  # unknown type
        "spBv1.0/+/NDATA/e",  # wildcards
        "spBv1.0/plant/NDATA/#",
        "spBv1.0/plant/DDATA/e/+",
        "spBv1.0//NDATA/e",  # an empty level
        "spBv1.0/STATE/",
        "",
    ],
)
def test_bad_topics_raise(bad):
    with pytest.raises(SparkplugError):
        parse_topic(bad)


@pytest.mark.parametrize(
    "args",
    [
        ("pl/ant", "NDATA", "e"),
        ("plant", "NDATA", "e+"),
        ("plant", "DDATA", "e", "#"),
        ("plant", "DDATA", "e"),
        ("plant", "NDATA", "e", "d"),
        ("plant", "XDATA", "e"),
        ("", "NDATA", "e"),
        ("plant", "STATE", "scada"),
    ],
)
def test_bad_topic_parts_raise(args):
    with pytest.raises(SparkplugError):
        topic(*args)


# --- aliases ----------------------------------------------------------------------------------


def test_a_birth_carries_name_and_alias_data_the_alias_only():
    defs = [(MetricDef("Axis/z/correction_um", D.Double, "µm"), -1.25), (MetricDef("State", D.String), "running")]
    aliases = {"Axis/z/correction_um": 7, "State": 300}
    birth = decode(encode(defs, timestamp_ms=1, seq=0, with_properties=True, aliases=aliases))
    assert [(m.name, m.alias, m.datatype) for m in birth.metrics] == [
        ("Axis/z/correction_um", 7, D.Double),
        ("State", 300, D.String),
    ]
    data = encode(defs, timestamp_ms=2, seq=1, aliases=aliases, names=False)
    got = decode(data)
    assert [(m.name, m.alias, m.value, m.datatype) for m in got.metrics] == [
        (None, 7, -1.25, D.Double),
        (None, 300, "running", D.String),
    ]
    raw = PayloadMessage.FromString(data).metrics
    assert not raw[0].HasField("name") and raw[0].alias == 7  # no name on the wire at all
    # the wire bytes of an aliased data metric: alias (field 2), datatype (4), double (13)
    assert encode([defs[0]], timestamp_ms=2, seq=1, aliases={"Axis/z/correction_um": 7}, names=False) == (
        vint(1, 2) + vlen(2, vint(2, 7) + vint(4, 10) + key(13, 1) + struct.pack("<d", -1.25)) + vint(3, 1)
    )
    # a metric without an alias cannot go in a message by alias; a message by alias needs aliases
    with pytest.raises(SparkplugError, match="has no alias"):
        encode(defs, timestamp_ms=2, seq=1, aliases={"State": 300}, names=False)
    with pytest.raises(SparkplugError, match="needs aliases"):
        encode(defs, timestamp_ms=2, seq=1, names=False)
    with pytest.raises(SparkplugError, match="alias"):
        encode(defs, timestamp_ms=2, seq=1, aliases={"State": -1})


def test_the_alias_table_is_unique_across_the_node_and_stable():
    table = AliasTable()
    node = table.declare(None, ["bdSeq", "Node Control/Rebirth", "Model/result"])
    dev = table.declare("m1", ["Sample", "Model/result", "State"])
    assert "Node Control/Rebirth" not in node and {"Node Control/Rebirth"} == UNALIASED
    assert node == {"bdSeq": 1, "Model/result": 2}
    assert dev == {"Sample": 3, "Model/result": 4, "State": 5}  # the same name on the device: another alias
    # a rebirth with a metric more (and one fewer) keeps every alias; the new one gets the next
    again = table.declare("m1", ["Sample", "Signal/T_new/value", "State"])
    assert again == {"Sample": 3, "Signal/T_new/value": 6, "State": 5}
    assert table.declare(None, ["Model/result", "bdSeq"]) == {"Model/result": 2, "bdSeq": 1}
    assert table.name(None, 2) == "Model/result" and table.name("m1", 4) == "Model/result"
    assert table.name("m1", 1) is None and table.name(None, 3) is None and table.name(None, 99) is None
    assert table.name(None, "2") is None and len(table) == 6


def test_a_host_resolves_aliases_from_the_births():
    nb = encode(
        [(MetricDef("bdSeq", D.UInt64), 0), (MetricDef("Telemetry/dropped", D.UInt64), 0)],
        timestamp_ms=1,
        seq=0,
        aliases={"bdSeq": 1, "Telemetry/dropped": 2},
    )
    db = encode(
        [(MetricDef("Sample", D.UInt64), 1), (MetricDef("Word", D.UInt16), 0), (MetricDef("Off", D.Int8), 0)],
        timestamp_ms=1,
        seq=1,
        aliases={"Sample": 3, "Word": 4, "Off": 5},
    )
    host = AliasResolver()
    assert host.resolve("spBv1.0/g/NBIRTH/e", decode(nb)) == []
    assert host.resolve("spBv1.0/g/DBIRTH/e/m1", decode(db)) == []
    data = decode(
        encode(
            [(MetricDef("Word", D.UInt16), 0x4543), (MetricDef("Sample", D.UInt64), 9)],
            timestamp_ms=2,
            seq=2,
            aliases={"Word": 4, "Sample": 3},
            names=False,
        )
    )
    assert host.resolve("spBv1.0/g/DDATA/e/m1", data) == []
    assert [(m.name, m.value) for m in data.metrics] == [("Word", 0x4543), ("Sample", 9)]
    # an alias of the node is not one of the device's; one no birth gave stays nameless
    stray = decode(
        encode(
            [(MetricDef("x", D.UInt64), 1), (MetricDef("y", D.UInt64), 1)],
            timestamp_ms=2,
            seq=3,
            aliases={"x": 2, "y": 77},
            names=False,
        )
    )
    assert host.resolve("spBv1.0/g/DDATA/e/m1", stray) == [2, 77] and stray.metrics[0].name is None
    node = decode(encode([(MetricDef("x", D.UInt64), 5)], timestamp_ms=2, seq=4, aliases={"x": 2}, names=False))
    assert host.resolve("spBv1.0/g/NDATA/e", node) == [] and node.metrics[0].name == "Telemetry/dropped"
    # a metric sent without its datatype takes the birth's (a signed one read as such)
    untyped = PayloadMessage(timestamp=3, seq=5)
    untyped.metrics.add(alias=5, int_value=255)
    p = decode(untyped.SerializeToString())
    assert p.metrics[0].datatype is D.Unknown and host.resolve("spBv1.0/g/DDATA/e/m1", p) == []
    assert (p.metrics[0].name, p.metrics[0].datatype, p.metrics[0].value) == ("Off", D.Int8, -1)
    wrong = PayloadMessage(timestamp=3, seq=6)
    wrong.metrics.add(alias=4, string_value="not a word")
    with pytest.raises(SparkplugError, match="not a UInt16"):
        host.resolve("spBv1.0/g/DDATA/e/m1", decode(wrong.SerializeToString()))
    # a new NBIRTH (a new session) forgets the device's birth until its DBIRTH comes again
    host.resolve("spBv1.0/g/NBIRTH/e", decode(nb))
    again = decode(encode([(MetricDef("Word", D.UInt16), 1)], timestamp_ms=4, seq=2, aliases={"Word": 4}, names=False))
    assert host.resolve("spBv1.0/g/DDATA/e/m1", again) == [4]
    with pytest.raises(SparkplugError):
        host.resolve("not/sparkplug", again)

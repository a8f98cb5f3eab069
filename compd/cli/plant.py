"""The plant's commands: `compd sparkplug-watch`, what the broker carries from compd's Sparkplug B topics, decoded."""

from __future__ import annotations

import argparse
import datetime as dt
import json
import math
import sys
import time
from typing import Any, TextIO

from compd.cli.args import command, positive
from compd.core.errors import BadInput

CONNECT_TIMEOUT_S = 10.0  # for the broker to accept the connection


def _watched(config: str) -> tuple[Any, str, str]:
    """The broker of CONFIG's telemetry section (its files read as the daemon reads them), its group and edge node."""
    from compd.config import load_config
    from compd.plant.spec import broker_spec

    cfg = load_config(config)
    tel = cfg.top.telemetry
    if tel is None:
        raise BadInput("the config has no telemetry section: give --host instead", file=config, path="telemetry")
    return broker_spec(cfg), tel.group_id, tel.edge_node_id


def _value(v: Any) -> str:
    if v is None:
        return "null"
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, float):
        return "NaN" if math.isnan(v) else f"{v:.6g}"
    if isinstance(v, str):
        return json.dumps(v, ensure_ascii=False)
    return str(v)


def _stamp(ms: int | None) -> str:
    if ms is None:
        return "no timestamp"
    return dt.datetime.fromtimestamp(ms / 1000.0, dt.UTC).strftime("%Y-%m-%d %H:%M:%S.%f")[:-3] + " UTC"


class RebirthGate:
    """What a watch that asked a node for its births shows: everything, except the node's own messages that
    were sent before its birth came (data by aliases no birth names yet, and the old sequence). The node's
    NBIRTH opens the gate; the NCMD that asked for it passes."""

    def __init__(self, group: str | None, node: str | None) -> None:
        self.group, self.node = group, node
        self.born = group is None or node is None
        self.held = 0  # messages of the node left out before its birth

    def admit(self, topic: str) -> bool:
        if self.born:
            return True
        from compd.plant.sparkplug import SparkplugError, parse_topic

        try:
            group, kind, node, _device = parse_topic(topic)
        except SparkplugError:
            return True
        if (group, node) != (self.group, self.node) or kind == "NCMD":
            return True
        if kind == "NBIRTH":
            self.born = True
            return True
        self.held += 1
        return False


def describe(topic: str, data: bytes, resolver: Any, units: dict[tuple[str, str], str], out: TextIO) -> None:
    """Print one message: its topic, seq and time, then a line per metric (name, value with the unit
    its birth gave, datatype). A metric that came by an alias no birth seen here declared is printed
    by its alias. `units` keeps the births' units, by (node or device topic, metric name)."""
    from compd.plant.sparkplug import SparkplugError, decode, parse_topic

    try:
        group, kind, node, device = parse_topic(topic)
    except SparkplugError as e:
        print(f"{topic}: not a Sparkplug B topic ({e})", file=out)
        return
    if kind == "STATE":
        text = data[:200].decode("utf-8", "replace")
        print(f"{topic} {text}", file=out)
        return
    try:
        payload = decode(data)
        unknown = resolver.resolve(topic, payload)
    except SparkplugError as e:
        print(f"{topic}: cannot decode ({e})", file=out)
        return
    seq = "" if payload.seq is None else f" seq {payload.seq}"
    by_alias = sum(1 for m in payload.metrics if m.alias is not None)
    how = f", {by_alias} by alias" if by_alias and not kind.endswith("BIRTH") else ""
    n = len(payload.metrics)
    print(f"{topic}{seq} ({n} metric{'' if n == 1 else 's'}{how}, {_stamp(payload.timestamp_ms)})", file=out)
    where = f"{group}/{node}/{device or ''}"
    for m in payload.metrics:
        name = m.name if m.name is not None else f"alias {m.alias}"
        unit = m.properties.get("engUnit")
        if kind.endswith("BIRTH") and isinstance(unit, str):
            units[(where, name)] = unit
        elif not kind.endswith("BIRTH"):
            unit = units.get((where, name))
        value = _value(m.value) + (f" {unit}" if isinstance(unit, str) and m.value is not None else "")
        alias = f", alias {m.alias}" if m.alias is not None and kind.endswith("BIRTH") else ""
        print(f"  {name} = {value}  ({m.datatype.name}{alias})", file=out)
    if unknown:
        print(
            f"  (aliases {', '.join(map(str, unknown))}: no birth of this node seen since the watch began;"
            " its next birth, or a rebirth, names them)",
            file=out,
        )


def args_sparkplug_watch(sub: Any) -> None:
    """`compd sparkplug-watch`'s arguments."""
    s = sub.add_parser(
        "sparkplug-watch",
        help="print what compd publishes on the plant's MQTT broker, decoded",
        description="Subscribe to the Sparkplug B topics of a group (the config's telemetry section says where"
        " and how, or --host) and print every message decoded: births with each metric's alias,"
        " data by name (aliases resolved from the births seen), deaths, STATE. Exit 0 after"
        " --count messages, 1 when none came within --timeout-s or the broker cannot be reached.",
        epilog="example:\n  compd sparkplug-watch --config /etc/compd/compd.yaml --count 3\n"
        "  compd sparkplug-watch --host 127.0.0.1 --port 1883 --group hall2",
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    s.add_argument(
        "--config", default=None, metavar="CONFIG", help="take broker, TLS, user and group from its telemetry section"
    )
    s.add_argument("--host", default=None, help="the broker (without --config; plain TCP, no user)")
    s.add_argument("--port", type=int, default=1883, help="the broker's port with --host (default 1883)")
    s.add_argument(
        "--group",
        default=None,
        metavar="GROUP",
        help="the Sparkplug group to watch (default: the config's group_id, else every group)",
    )
    s.add_argument(
        "--node",
        default=None,
        metavar="EDGE_NODE",
        help="the edge node --rebirth asks (default: the config's edge_node_id)",
    )
    s.add_argument(
        "--rebirth",
        action="store_true",
        help="ask the edge node for its births first (an NCMD Node Control/Rebirth, as a Sparkplug host"
        " that joins late does), so that its data can be shown by name; what the node sent before its"
        " birth is left out (and not counted)",
    )
    s.add_argument("--count", type=int, default=None, metavar="N", help="stop after N messages (default: until Ctrl-C)")
    s.add_argument(
        "--timeout-s",
        type=positive,
        default=None,
        dest="timeout_s",
        metavar="S",
        help="give up (exit 1) when S seconds pass without a message",
    )


def _ask_rebirth(client: Any, group: str, node: str) -> None:
    """Publish NCMD `Node Control/Rebirth` = true to the edge node, once the subscription is in place."""
    from compd.plant.sparkplug import DataType, MetricDef, encode, topic

    payload = encode(
        [(MetricDef("Node Control/Rebirth", DataType.Boolean), True)], timestamp_ms=int(time.time() * 1000), seq=None
    )
    client.publish(topic(group, "NCMD", node), payload, qos=1)
    print(f"compd: asked {group}/{node} for its births", file=sys.stderr, flush=True)


@command("sparkplug-watch", args_sparkplug_watch)
def cmd_sparkplug_watch(args: argparse.Namespace) -> int:
    if (args.config is None) == (args.host is None):
        raise BadInput("give --config or --host (one of them)")
    if args.count is not None and args.count < 1:
        raise BadInput("--count must be at least 1", path="--count")
    if not 1 <= args.port <= 65535:
        raise BadInput("--port must be 1..65535", path="--port")
    try:
        import paho.mqtt.client as mqtt

        from compd.plant.sparkplug import NAMESPACE, AliasResolver
        from compd.plant.spec import BrokerSpec
        from compd.plant.telemetry import log_in
    except ImportError:
        from compd.core.registry import install_hint

        raise BadInput(f"needs the plant extra: {install_hint('plant')}") from None
    if args.config is not None:
        broker, group, node = _watched(args.config)
    else:
        broker, group, node = BrokerSpec(host=args.host, port=args.port), None, None
    group, node = args.group or group, args.node or node
    if args.rebirth and not (group and node):
        raise BadInput(
            "--rebirth needs the group and the edge node: give --config, or --group and --node", path="--rebirth"
        )
    topic = f"{NAMESPACE}/{group}/#" if group else f"{NAMESPACE}/#"
    inbox: list[tuple[str, bytes]] = []
    connected: list[Any] = []

    client = mqtt.Client(mqtt.CallbackAPIVersion.VERSION2, clean_session=True)
    log_in(client, broker)
    client.on_connect = lambda c, _u, _f, rc, _p: connected.append(rc)
    client.on_message = lambda _c, _u, msg: inbox.append((msg.topic, bytes(msg.payload)))
    where = f"{broker.host}:{broker.port}"
    try:
        client.connect(broker.host, broker.port, keepalive=30)
    except OSError as e:
        print(f"compd: cannot reach the broker at {where}: {e.strerror or e}", file=sys.stderr)
        return 1
    resolver = AliasResolver()
    units: dict[tuple[str, str], str] = {}
    seen = 0
    try:
        deadline = time.monotonic() + CONNECT_TIMEOUT_S
        while not connected:
            client.loop(timeout=0.1)
            if time.monotonic() > deadline:
                print(
                    f"compd: the broker at {where} did not accept the connection within {CONNECT_TIMEOUT_S:g} s",
                    file=sys.stderr,
                )
                return 1
        if connected[0].is_failure:
            print(f"compd: the broker at {where} refused the connection: {connected[0]}", file=sys.stderr)
            return 1
        client.subscribe(topic, qos=1)
        print(f"compd: watching {topic} on {where}", file=sys.stderr, flush=True)
        if args.rebirth:
            _ask_rebirth(client, group, node)
        gate = RebirthGate(group, node) if args.rebirth else RebirthGate(None, None)
        quiet_since = time.monotonic()
        while args.count is None or seen < args.count:
            rc = client.loop(timeout=0.2)
            if rc != mqtt.MQTT_ERR_SUCCESS:
                print(f"compd: lost the broker at {where} ({mqtt.error_string(rc)})", file=sys.stderr)
                return 1
            while inbox and (args.count is None or seen < args.count):
                t, data = inbox.pop(0)
                if not gate.admit(t):
                    continue
                if gate.held and gate.born:
                    print(
                        f"compd: left out {gate.held} message{'' if gate.held == 1 else 's'} of {group}/{node} sent"
                        " before its birth (by aliases no birth seen here names)",
                        file=sys.stderr,
                        flush=True,
                    )
                    gate.held = 0
                describe(t, data, resolver, units, sys.stdout)
                sys.stdout.flush()
                seen += 1
                quiet_since = time.monotonic()
            if args.timeout_s is not None and time.monotonic() - quiet_since > args.timeout_s:
                if not gate.born:
                    print(
                        f"compd: no birth of {group}/{node} for {args.timeout_s:g} s after the rebirth was asked"
                        f" ({gate.held} of its messages left out, {seen} shown)",
                        file=sys.stderr,
                    )
                    return 1
                print(f"compd: no message on {topic} for {args.timeout_s:g} s ({seen} seen)", file=sys.stderr)
                return 1
    finally:
        client.disconnect()
    return 0

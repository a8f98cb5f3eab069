"""`python -m hil_sim serve --config FILE`: start the devices a YAML file describes, until Ctrl-C.

The file is a list of devices (like pyvisa-sim's device files), each a mapping with
`kind` and `name`:

* `pt100_modbus` — a PT100 Modbus module (`transport: tcp` with `host`/`port`, or
  `rtu` with `serial_port`); `pty_link: PATH` makes a socat pair and serves on
  `serial_port`, so compd opens `pty_link`. Options of `Pt100ModbusDevice`.
* `dcon` — an ADAM-4015-style DCON module on `serial_port` (with `pty_link` likewise).
* `can_pt100` — temperatures broadcast on a python-can bus (`interface`, `channel`).
* `fanuc_pmc` — compd's software PLC PMC (compd.plc) served on Modbus TCP (`host`, `port`,
  `scan_s`, `step_limit_um`, `device_id`).
* `siemens_nc` — compd's software PLC NC temperature-compensation data (compd.plc) served on
  Modbus TCP (`axes`, `ipo_s`, `max_velo_mm_min`, `velo_factor`).
* `linuxcnc_hal` — a running LinuxCNC seen through HAL (hil_sim.devices.linuxcnc_hal: `axes`,
  `component`, `speed_pin`): a plant that names it as `cnc` turns at LinuxCNC's spindle speed
  and gets the external offsets LinuxCNC applies (read from HAL).
* `plant` — a live plant for the closed loop (hil_sim.devices.plant): `scenario` (file),
  `speedup` (plant s per wall s), `start` (immediate / on_clock_read), `log_path` and
  `log_period_s` (the residual log), `duration_s`, `seed`, `cnc` (name of the PMC or NC
  device whose applied correction reaches the plant) and `cnc_axes` (plant axis → CNC
  axis); its clock and signals on Modbus TCP (`host`, `port`, `device_id`). Opt-in
  probing: `probe_every_s`, `probe_axes`, `probe_sigma_um` (0.3), `probe_outliers`
  ([plant time s, µm] pairs), `probe_seed`: the machine's probing cycle publishes the
  residual it measures through its CNC's probe-result block.

A transmitter (`pt100_modbus`, `dcon`, `can_pt100`) with `plant: NAME` reads its channels
(by name) from that plant. A `fanuc_pmc` or `siemens_nc` with `clock: plant` scans on
the plant's time (the plant that names it as `cnc` advances it) instead of wall time.
Plants are started after every other device.

Ports 0 pick a free port; every device prints where it listens.
"""

from __future__ import annotations

import signal
import sys
import threading
from collections.abc import Callable
from pathlib import Path
from typing import Any, TextIO

import yaml

KINDS = ("pt100_modbus", "dcon", "can_pt100", "fanuc_pmc", "siemens_nc", "linuxcnc_hal", "plant")
CLOCKS = ("wall", "plant")


class Running:
    """One device's started parts, stopped in reverse order."""

    def __init__(self, name: str, kind: str) -> None:
        self.name = name
        self.kind = kind
        self.parts: list[Any] = []
        self.where: Callable[[], str] = lambda: ""
        self.device: Any = None
        self.feed_plant: str | None = None  # transmitters fed by a plant
        self.clock = "wall"  # CNCs: wall or plant

    def start(self, part: Any) -> Any:
        part.start()
        self.parts.append(part)
        return part

    def stop(self) -> None:
        for p in reversed(self.parts):
            p.stop()
        self.parts.clear()


def _pty(run: Running, cfg: dict[str, Any]) -> None:
    link = cfg.pop("pty_link", None)
    if link is not None:
        from hil_sim.devices.ptypair import PtyPair

        run.start(PtyPair(cfg["serial_port"], link))


def start_device(cfg: dict[str, Any]) -> Running:
    """Build and start one device from its section."""
    cfg = dict(cfg)
    kind = cfg.pop("kind", None)
    name = str(cfg.pop("name", kind))
    if kind not in KINDS:
        raise ValueError(f"device {name!r}: unknown kind {kind!r} (known: {', '.join(KINDS)})")
    run = Running(name, kind)
    if kind in ("pt100_modbus", "dcon", "can_pt100"):
        run.feed_plant = cfg.pop("plant", None)
    if kind in ("fanuc_pmc", "siemens_nc"):
        run.clock = cfg.pop("clock", "wall")
        if run.clock not in CLOCKS:
            raise ValueError(f"device {name!r}: clock must be wall or plant, got {run.clock!r}")
    try:
        if kind == "plant":
            raise ValueError(f"device {name!r}: a plant is started by serve() after the other devices")
        if kind == "pt100_modbus":
            from hil_sim.devices import pt100_modbus

            _pty(run, cfg)
            link = run.parts[0].b if run.parts else None
            tx, dev, srv = pt100_modbus.from_config(cfg)
            run.device = tx
            run.start(srv)
            run.where = lambda: srv.where() + (f" (compd opens {link})" if link else "")
        elif kind == "dcon":
            from hil_sim.devices.dcon import DconModule

            _pty(run, cfg)
            link = run.parts[0].b if run.parts else None
            tx, mod = DconModule.from_config(cfg)
            run.device = tx
            run.start(mod)
            run.where = lambda: mod.where() + (f" (compd opens {link})" if link else "")
        elif kind == "linuxcnc_hal":
            from hil_sim.devices.linuxcnc_hal import LinuxcncHal

            hal_dev = LinuxcncHal(**cfg)
            run.device = hal_dev
            run.start(hal_dev)
            run.where = hal_dev.where
        elif kind == "can_pt100":
            from hil_sim.devices.can_pt100 import CanPt100

            tx, dev = CanPt100.from_config(cfg)
            run.device = tx
            run.start(dev)
            run.where = dev.where
        else:  # a CNC: fanuc_pmc or siemens_nc, a Modbus server and (on wall time) its scan thread
            from compd.plc.fanuc_pmc import FanucPmc
            from compd.plc.siemens_nc import SiemensNc
            from hil_sim.devices.modbus_server import ModbusServerThread
            from hil_sim.devices.scan import NcIpoThread, PmcScanThread

            host, port, dev_id = cfg.pop("host", "127.0.0.1"), int(cfg.pop("port", 0)), int(cfg.pop("device_id", 1))
            if kind == "fanuc_pmc":
                cnc: Any = FanucPmc(**cfg)
                scan, label = PmcScanThread(cnc), f" scan {cnc.scan_s * 1000:g} ms"
            else:
                cnc = SiemensNc(**cfg)
                scan, label = NcIpoThread(cnc), f" IPO {cnc.ipo_s * 1000:g} ms"
            run.device = cnc
            if run.clock == "wall":
                run.start(scan)
            srv = run.start(ModbusServerThread(cnc, host=host, port=port, device_id=dev_id))
            run.where = lambda: srv.where() + label
    except BaseException:
        run.stop()
        raise
    return run


def start_plant(cfg: dict[str, Any], others: dict[str, Running], base_dir: Path) -> Running:
    """Build and start a `plant` device; wire its CNC and the transmitters that name it."""
    from hil_sim.devices.modbus_server import ModbusServerThread
    from hil_sim.devices.plant import PlantDevice
    from hil_sim.logcmd import load_plant

    cfg = dict(cfg)
    cfg.pop("kind")
    name = str(cfg.pop("name", "plant"))
    scenario = Path(cfg.pop("scenario"))
    if not scenario.is_absolute():
        scenario = base_dir / scenario
    plant = load_plant(str(scenario), cfg.pop("seed", None))
    host, port, dev_id = cfg.pop("host", "127.0.0.1"), int(cfg.pop("port", 0)), int(cfg.pop("device_id", 1))
    cnc_name, cnc_axes = cfg.pop("cnc", None), cfg.pop("cnc_axes", None)
    dev = PlantDevice(plant, **cfg)
    if cnc_name is not None:
        cnc = others.get(cnc_name)
        if cnc is None or cnc.kind not in ("fanuc_pmc", "siemens_nc", "linuxcnc_hal"):
            raise ValueError(f"plant {name!r}: cnc {cnc_name!r} is not a fanuc_pmc, siemens_nc or linuxcnc_hal device")
        dev.attach_cnc(cnc.device, cnc.kind, cnc_axes, cnc.clock == "plant")
        if cnc.kind == "linuxcnc_hal":  # LinuxCNC runs the program: the plant turns at its spindle's speed
            plant.speed_from = cnc.device.speed_rpm
    for other in others.values():
        if other.feed_plant == name:
            other.device.feed = dev.feed_for(other.device.names)
    run = Running(name, "plant")
    run.device = dev
    try:
        run.start(dev)
        srv = run.start(ModbusServerThread(dev, host=host, port=port, device_id=dev_id))
    except BaseException:
        run.stop()
        raise
    run.where = lambda: srv.where() + f" {dev.where()}"
    return run


def load(path: str | Path) -> list[dict[str, Any]]:
    data = yaml.safe_load(Path(path).read_text(encoding="utf-8"))
    devices = data.get("devices") if isinstance(data, dict) else None
    if not isinstance(devices, list) or not all(isinstance(d, dict) for d in devices):
        raise ValueError(f"{path}: expected a mapping with a 'devices' list")
    return devices


def serve(path: str | Path, out: TextIO = sys.stdout, stop: threading.Event | None = None) -> int:
    """Start every device, print where each listens, run until `stop` (or SIGINT/SIGTERM)."""
    stop = stop or threading.Event()
    running: list[Running] = []
    try:
        cfgs = load(path)
        for cfg in [c for c in cfgs if c.get("kind") != "plant"]:
            run = start_device(cfg)
            running.append(run)
            print(f"{run.name}: {run.kind} on {run.where()}", file=out, flush=True)
        others = {r.name: r for r in running}
        for cfg in [c for c in cfgs if c.get("kind") == "plant"]:
            run = start_plant(cfg, others, Path(path).parent)
            running.append(run)
            print(f"{run.name}: {run.kind} on {run.where()}", file=out, flush=True)
        for r in running:
            if r.feed_plant is not None and r.device.feed is None:
                raise ValueError(f"device {r.name!r}: plant {r.feed_plant!r} is not in the file")
        print("hil_sim: ready (Ctrl-C stops)", file=out, flush=True)
        while not stop.wait(0.2):
            pass
    finally:
        for run in reversed(running):
            run.stop()
        print("hil_sim: stopped", file=out, flush=True)
    return 0


def main(args: Any) -> int:
    """The `serve` subcommand."""
    stop = threading.Event()
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, lambda *_: stop.set())
    try:
        return serve(args.config, stop=stop)
    except (OSError, ValueError, TypeError, RuntimeError) as e:
        print(f"hil_sim: {e}", file=sys.stderr)
        return 2

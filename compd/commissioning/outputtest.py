"""`compd output-test`: a known correction through the configured sink, read back, ramped at the guard's slew.

The sign check before enabling the output: the correction walks up to `um` at the
axis's slew limit (the config's guard, never faster than one period's slew per cycle,
however late a cycle runs), is held for `hold_s`, what the device reports as applied
is read back, and the correction walks back to zero at the same slew before the sink
is put in its safe state. The stages are the daemon's own, wired by the one pipeline
builder (compd/cycle/pipeline.py) and stepped by the loop's own cycle: the guard (clamp,
slew), the codec's word, the configured sink and its device; only the model is
replaced by the fixed correction (`FixedCorrection`) and there are no sources. A device
of the software PLC in process runs on simulated time, one over the network on the wall
clock.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from compd.config import Config
from compd.core.clock import Clock, SimClock, WallClock
from compd.core.config import Strict
from compd.core.errors import BadInput
from compd.cycle.pipeline import build_pipeline
from compd.models.base import Model
from compd.service.status import daemon_status_path, held, read_status
from compd.sinks.base import Sink

SETTLE_CYCLES = 3  # cycles run after a ramp reached its goal, so the sink delivers the last step
DEVICE_WAIT_S = 2.0  # then at most this long for the device to report the goal as applied
SAFE_WAIT_S = 0.5  # after the safe state, before the last read-back (an NC ramps what is left)
LINK_WAIT_S = 3.0  # the device must answer this soon after the sink opens, or nothing is written


class DeviceUnreachable(Exception):
    """The sink's device did not answer: the test wrote nothing (exit 1)."""


class FixedCorrection(Model):
    """The model of an output test: no inputs, and the prediction the test sets (`pred_um`,
    NaN for the axes it does not drive: the guard holds those at their fault policy)."""

    kind = "output_test"
    Params = Strict

    def __init__(self, outputs: list[str]) -> None:
        super().__init__(Strict(), [], outputs)
        self.pred_um = np.full(len(outputs), math.nan)

    def evaluate(self, x: np.ndarray, t_s: float, out: np.ndarray) -> None:
        out[:] = self.pred_um


@dataclass
class OutputTestResult:
    """What was commanded and what the device applied, with the trace of every cycle."""

    axis: str
    device: str
    commanded_um: float
    applied_um: float  # read back at the end of the hold
    applied_after_um: float  # read back after the ramp down and the safe state
    slew_um_per_s: float
    period_s: float
    word: int  # the word held during the hold
    resolution_um: float
    t_s: list[float] = field(default_factory=list)
    correction_um: list[float] = field(default_factory=list)  # the guard's output per cycle
    device_um: list[float] = field(default_factory=list)  # what the device reported per cycle
    interrupted: bool = False

    @property
    def max_step_um(self) -> float:
        """The largest change of the correction between two cycles."""
        c = np.asarray(self.correction_um)
        return float(np.max(np.abs(np.diff(c)))) if c.size > 1 else 0.0

    def matches(self, resolution_um: float) -> bool:
        """Applied is commanded, within the device's resolution (the word's LSB, the NC's
        smallest change sent), with the same sign."""
        ok = abs(self.applied_um - self.commanded_um) <= resolution_um + 1e-6
        return ok and math.copysign(1.0, self.applied_um) == math.copysign(1.0, self.commanded_um)

    def as_dict(self) -> dict[str, Any]:
        return {
            "axis": self.axis,
            "device": self.device,
            "commanded_um": self.commanded_um,
            "applied_um": self.applied_um,
            "applied_after_um": self.applied_after_um,
            "slew_um_per_s": self.slew_um_per_s,
            "period_s": self.period_s,
            "max_step_um": self.max_step_um,
            "word": f"0x{self.word:04X}",
            "interrupted": self.interrupted,
            "resolution_um": self.resolution_um,
            "matches": self.matches(self.resolution_um),
        }


def axis_limits(cfg: Config, axis: str) -> tuple[float, float]:
    """The guard's clamp and slew limit of `axis` (its override, else the guard's), µm and µm/s."""
    return cfg.guard.clamp_um(axis)[0], cfg.guard.slew_um_per_s(axis)


def build_sink(cfg: Config) -> tuple[Sink, list[str], list[str]]:
    """The configured sink (not opened, not yet bound: the pipeline binds it), the model's
    outputs and the word's axes."""
    sink_cls, sink_cfg, path = cfg.sink
    sink: Sink = sink_cls(sink_cfg, base_dir=str(Path(cfg.file).parent))
    sink.config_path = path
    outputs = list(cfg.model.outputs)
    return sink, outputs, list(cfg.codec.axes or outputs[:2])


def check_request(cfg: Config, sink: Sink, word_axes: list[str], axis: str, um: float) -> None:
    """Bad input (exit 2): an axis the sink does not drive, a correction beyond the guard's
    clamp or the device's range, or one the word would send as disabled."""
    if axis not in word_axes:
        raise BadInput(
            f"{axis!r} is not an axis the sink drives (known: {', '.join(word_axes)})", path="--axis", file=cfg.file
        )
    max_abs, _ = axis_limits(cfg, axis)
    if abs(um) > max_abs:
        raise BadInput(
            f"|{um:g}| um is beyond the guard's max correction of axis {axis} ({max_abs:g} um)",
            path="--um",
            file=cfg.file,
        )
    dev = sink.device_info()
    if dev["max_abs_um"] is not None and abs(um) > dev["max_abs_um"]:
        raise BadInput(
            f"|{um:g}| um is beyond what {dev['device']} carries ({dev['max_abs_um']:g} um)", path="--um", file=cfg.file
        )
    if dev["max_abs_um"] is not None and abs(um) <= cfg.codec.deadband_um:
        raise BadInput(
            f"{um:g} um is inside the codec's dead-band ({cfg.codec.deadband_um:g} um): nothing would be sent",
            path="--um",
            file=cfg.file,
        )
    if um == 0:
        raise BadInput("give a correction other than 0", path="--um", file=cfg.file)


def running_daemon(cfg: Config) -> str | None:
    """Why a daemon of this config seems to hold the sink's device now (its status file is
    fresh, its process exists; also with its cycle stale: stopped, it may run again), or None:
    the test must not write beside a running loop."""
    path = daemon_status_path(cfg)
    if not path.is_file():
        return None
    try:
        data = read_status(path)
        alive = held(data)
    except (BadInput, TypeError, ValueError):
        return None
    return f"a daemon of this config is running (pid {data.get('pid')}, {path}): stop it first" if alive else None


def run_output_test(
    cfg: Config,
    axis: str,
    um: float,
    hold_s: float = 5.0,
    *,
    clock: Clock | None = None,
    say: Callable[[str], None] = print,
) -> OutputTestResult:
    """Ramp `axis` to `um` at the guard's slew, hold, read back, ramp to zero, safe state.

    `clock`: default simulated time for a device of the software PLC in process, the
    wall clock for one over the network."""
    sink, outputs, word_axes = build_sink(cfg)
    period_s = cfg.loop.period_s
    if clock is None:
        clock = SimClock(0.0) if sink.device_key() is None else WallClock(cfg.loop.spin_margin_s)
    model = FixedCorrection(outputs)
    # the daemon's pipeline, its model replaced by the fixed correction (no sources: no signals to check)
    p = build_pipeline(
        sources=[],
        model=model,
        sink=sink,
        clock=clock,
        period_s=period_s,
        guard_cfg=cfg.guard.model_copy(update={"signals": {}}),
        codec_cfg=cfg.codec,
    )
    loop, guard, encoder = p.loop, p.guard, p.encoder
    check_request(cfg, sink, word_axes, axis, um)
    a = outputs.index(axis)
    slot = word_axes.index(axis)
    guard.max_dt_s = period_s  # a late cycle never licenses more than one period's slew
    _, slew = axis_limits(cfg, axis)
    pred = model.pred_um
    dev_um = np.zeros(2)
    info = sink.device_info()
    res = OutputTestResult(
        axis, info["device"], um, math.nan, math.nan, slew, period_s, 0, float(info["resolution_um"] or 0.0)
    )
    state = {"next": math.nan}

    def cycle() -> None:
        if state["next"] != state["next"]:
            state["next"] = clock.now()
        clock.wait_until(state["next"])
        now = clock.now()
        state["next"] = max(state["next"] + period_s, now)
        loop.step(now)  # model (the fixed correction), guard, codec, sink: the daemon's cycle
        sink.applied_um(dev_um)
        res.t_s.append(now)
        res.correction_um.append(float(guard.out_um[a]))
        res.device_um.append(float(dev_um[slot]))

    def ramp_to(goal_um: float) -> None:
        pred[a] = -goal_um  # the guard's target is −prediction
        left = 2 * math.ceil(abs(goal_um - float(guard.out_um[a])) / (slew * period_s)) + 1000
        while abs(float(guard.out_um[a]) - goal_um) > 1e-9 or not encoder.settled(slot):
            cycle()
            left -= 1
            if left < 0:
                raise RuntimeError(f"axis {axis} did not reach {goal_um:g} um at its slew")
        for _ in range(SETTLE_CYCLES):
            cycle()
        # the device follows at its own pace (the sink's update period, the NC's ramp)
        t_end = clock.now() + DEVICE_WAIT_S
        while abs(res.device_um[-1] - goal_um) > res.resolution_um + 1e-6 and clock.now() < t_end:
            cycle()

    def read_back() -> float:
        sink.settle(clock.now())
        sink.applied_um(dev_um)
        return float(dev_um[slot])

    clock.start()
    sink.open(clock.now())
    try:
        t_end = clock.now() + LINK_WAIT_S
        # up, and what the device holds read back: the ramp starts from what the machine applies
        while not (loop.sync_output(clock.now()) or sink.synced()) or sink.link_state() != "up":
            if clock.now() >= t_end:
                raise DeviceUnreachable(f"{info['device']} does not answer (link {sink.link_state()}): nothing written")
            clock.wait_until(clock.now() + 0.05)
        try:
            say(f"output-test: axis {axis} to {um:+.3f} um through {info['device']}, at {slew:g} um/s")
            ramp_to(um)
            say(
                f"  ramped up in {len(res.t_s)} cycles ({res.t_s[-1] - res.t_s[0]:.2f} s), largest step"
                f" {res.max_step_um:.4f} um (slew x period {slew * period_s:.4f} um)"
            )
            t_end = clock.now() + hold_s
            while clock.now() < t_end:
                cycle()
            res.word = encoder.word
            res.applied_um = read_back()
            say(
                f"  hold {hold_s:g} s: commanded {um:+.3f} um, applied {res.applied_um:+.3f} um"
                f" (word 0x{encoder.word:04X})"
            )
        except KeyboardInterrupt:
            res.interrupted = True
            say("  interrupted: ramping back to zero")
        ramp_to(0.0)
        sink.safe()
        clock.wait_until(clock.now() + SAFE_WAIT_S)
        res.applied_after_um = read_back()
        say(f"  ramped back to zero at {slew:g} um/s, safe state: applied {res.applied_after_um:+.3f} um")
    finally:
        sink.safe()
        sink.close()
        clock.stop()
    return res

"""Randomized families of simulated machines: one machine per seed, its physics, sensors and days drawn per machine.

`draw(kind, seed)` builds a `Machine` of one of hil_sim's plants (lathe, spindle, gantry,
feed_axis, vmc) with its parameters drawn around the plant's DEFAULTS, its sensors' lags,
cross-talk and placement drawn, and two days of duty drawn for it: a training day at one
or two speeds (feeds) with long runs and pauses, and an unseen day at other speeds, some
below and some above the training range, with runs, pauses and loads of random length and
size, in another ambient. Every range is in the tables below (RANGES, PLACEMENT, SENSORS,
NEIGHBOURS, DUTY, COMMON_DUTY, AMBIENT); the plants compute their own physics, nothing of
compd's models is used.

`draw(..., train="plan")` replaces the training day by the thermal test `compd testplan` designs
for the machine from what its builder knows (PLAN below): the type's speed range (or its axis's
stroke and feed range), the day's hours, compd's defaults otherwise; in the same ambient.

`python -m hil_sim family --kind KIND --seeds 1-20 --out DIR [--rate-s S] [--train plan]` writes
DIR/<kind>_<seed>_train.csv, DIR/<kind>_<seed>_unseen.csv (log CSVs as `hil_sim log`
writes them) and DIR/<kind>_<seed>_machine.yaml (what was drawn; its `train` and `unseen`
are scenario files' contents, so `hil_sim log` can rerun a day from them).
"""

from __future__ import annotations

import argparse
import math
import re
import zlib
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from compd.commissioning.testplan import Axis, design
from compd.core.errors import BadInput
from hil_sim.scenario import Ambient, Scenario, Segment, plan_segments

KINDS = ("lathe", "spindle", "gantry", "feed_axis")  # the families scripts/family.py fits and gates
# every kind `draw` and `hil_sim family` take: the VMC (two heat sources on one axis) is drawn too,
# but no physics model of compd's sums its two sources yet, so the harness leaves it out
ALL_KINDS = (*KINDS, "vmc")
DAY_S = 86400.0
# log periods per kind: the feed axis reciprocates in seconds, a spindle warms in minutes,
# AR(1) takes the lathe's log period as its Δτ (rig/closedloop.py's choices)
RATES_S = {"lathe": 60.0, "spindle": 10.0, "gantry": 30.0, "feed_axis": 10.0, "vmc": 10.0}

# ======================================================================================
# The ranges. A draw is (how, low, high):
#   factor   log-uniform factor on the plant's default (each element of a list)
#   log      log-uniform value
#   uniform  uniform value
# ======================================================================================
GAIN = ("factor", 0.6, 1.6)  # time constants and gains: convection, capacities, heat inputs, conductances
SIZE = ("factor", 0.8, 1.25)  # lengths and cross-sections of a machine of the same class
ALPHA = ("factor", 0.9, 1.12)  # expansion coefficients: steels and cast irons differ little
# motor currents (the copper loss goes with their square): the default axes lose so little that
# their working-day error is 2-8 µm; a machine a builder compensates grows 5-30 µm
CURRENT = ("factor", 1.0, 2.0)

_AXIS = {  # one linear-motor axis (hil_sim.plants.linear_axis), gantry sides and the feed axis
    "base_area_m2": SIZE,
    "base_perimeter_m": SIZE,
    "base_h_w_m2k": GAIN,
    "base_alpha_per_k": ALPHA,
    "support_g_w_k": GAIN,
    "support_restraint": ("uniform", 0.7, 1.0),
    "footprint_mm": SIZE,
    "motor_cap_j_k": GAIN,
    "motor_surface_m2": GAIN,
    "gap_g_w_k": GAIN,
    "motor_table_g_w_k": GAIN,
    "table_cap_j_k": GAIN,
    "table_surface_m2": GAIN,
    "table_alpha_per_k": ALPHA,
    "tool_offset_mm": SIZE,
    "h_w_m2k": GAIN,
    "h_speed_w_m2k_per_m_s": GAIN,
    "block_cap_j_k": GAIN,
    "block_table_g_w_k": GAIN,
    "block_rail_g_w_k": GAIN,
    "friction_w_per_m_min": GAIN,
    "head_cap_j_k": GAIN,
    "head_table_g_w_k": GAIN,
    "current_a": CURRENT,
    "current_a_per_m_min": CURRENT,
    "hold_current_a": CURRENT,
    "r_cu_ohm": GAIN,
}

_SPINDLE = {  # the motorized spindle, alone (spindle) or on a VMC's column (vmc)
    "length_mm": SIZE,
    "radius_mm": ("factor", 0.85, 1.15),
    "alpha_per_k": ALPHA,
    "conductivity_w_mk": ("factor", 0.8, 1.25),
    "front_w_per_krpm": GAIN,
    "rear_w_per_krpm": GAIN,
    "h_w_m2k": GAIN,
    "h_speed_w_m2k_per_krpm": ("uniform", 0.0, 3.0),
    "bearing_g_w_k": GAIN,
    "housing_outer_mm": ("factor", 0.9, 1.2),
    "housing_h_w_m2k": GAIN,
    "stator_w_per_krpm": GAIN,
    "coolant_g_w_k": GAIN,
    "coolant_offset_c": ("uniform", -1.5, 0.5),
    "axial_stiffness_n_per_um": ("factor", 0.7, 1.4),
}

RANGES: dict[str, dict[str, tuple[str, float, float]]] = {
    "lathe": {
        "spindle_length_mm": SIZE,
        "spindle_radius_mm": SIZE,
        "spindle_alpha_per_k": ALPHA,
        "spindle_h_w_m2k": GAIN,
        "spindle_h_w_m2k_per_krpm": GAIN,
        "front_bearing_w": GAIN,
        "rear_bearing_w": GAIN,
        "speed_exponent": ("uniform", 1.2, 1.9),
        "inner_share": ("uniform", 0.35, 0.65),
        "front_bearing_g_w_k": GAIN,
        "rear_bearing_g_w_k": GAIN,
        "headstock_area_m2": SIZE,
        "headstock_perimeter_m": SIZE,
        "headstock_h_w_m2k": GAIN,
        "drive_w": GAIN,
        "headstock_bed_g_w_k": GAIN,
        "bed_length_mm": SIZE,
        "bed_area_m2": SIZE,
        "bed_perimeter_m": SIZE,
        "bed_h_w_m2k": GAIN,
        "bed_alpha_per_k": ALPHA,
        "saddle_cap_j_k": GAIN,
        "saddle_surface_m2": SIZE,
        "saddle_bed_g_w_k": GAIN,
        "saddle_w": GAIN,
    },
    "spindle": dict(_SPINDLE),
    "gantry": {
        **_AXIS,
        "beam_cap_j_k": GAIN,
        "beam_surface_m2": SIZE,
        "beam_table_g_w_k": GAIN,
        "load_x1": ("uniform", 0.8, 1.2),
        "load_x2": ("uniform", 1.0, 1.4),
    },
    "feed_axis": dict(_AXIS),
    "vmc": {
        **_SPINDLE,
        "column_height_mm": SIZE,
        "column_area_m2": SIZE,
        "column_perimeter_m": SIZE,
        "column_alpha_per_k": ALPHA,
        "column_h_w_m2k": GAIN,
        "column_base_g_w_k": GAIN,
        "headstock_g_w_k": GAIN,
    },
}

# placement, sizes and the parts no sensor sees, drawn per kind (mm unless named otherwise)
PLACEMENT: dict[str, dict[str, Any]] = {
    "lathe": {
        # sensor offsets from the nominal places (T1, T2 on the headstock, T3-T5 on the bed)
        "T1_mm": ("uniform", -30.0, 30.0),
        "T2_mm": ("uniform", -30.0, 30.0),
        "T3_mm": ("uniform", -150.0, 150.0),
        "T4_mm": ("uniform", -60.0, 60.0),
        "T5_mm": ("uniform", -100.0, 100.0),
        "saddle_at_bed_share": ("uniform", 0.5, 0.7),  # where the saddle works, share of the bed
    },
    "spindle": {
        "xi_offset_share": ("uniform", -0.2, 0.2),  # ξ sensor off the mean-value point, share of the rotor
    },
    "gantry": {
        "column_p": 0.7,  # share of machines with an unmeasured column per side
        "column_cap_j_k": ("log", 20000.0, 120000.0),
        "column_surface_m2": ("uniform", 0.4, 1.5),
        "column_table_g_w_k": ("log", 1.0, 5.0),
        "column_beam_g_w_k": ("log", 0.3, 3.0),
        "column_lever_mm": ("uniform", 100.0, 400.0),
    },
    "feed_axis": {
        "stroke_mm": ("uniform", 600.0, 1200.0),  # the base is the stroke plus the default overhangs
        "base_sensor_mm": ("uniform", -30.0, 30.0),  # each base sensor off its nominal place
    },
    "vmc": {
        "xi_offset_share": ("uniform", -0.2, 0.2),  # as the spindle's
        # the column sensors off their nominal heights (the default's, scaled with the drawn height)
        "T_col_top_mm": ("uniform", -50.0, 50.0),
        "T_col_bot_mm": ("uniform", -50.0, 50.0),
    },
}

SENSORS = {
    "lag_s": ("log", 1.0, 300.0),  # each PT100 element behind its point
    "ambient_lag_s": ("log", 1.0, 20.0),  # the air sensor: a bare element in moving air
    "crosstalk_p": 0.5,  # share of the sensors (ambient aside) that also see a neighbour
    "crosstalk": ("uniform", 0.0, 0.3),  # the neighbour's share of the reading
}
AMBIENT_SENSOR = {"lathe": "T7", "spindle": "T_amb", "gantry": "T0", "feed_axis": "T_amb", "vmc": "T_amb"}

# what each sensor may also see: another sensor's point, or `body@x_mm` of the plant's network
# ({name} is a drawn position in mm: the sensor's own place `here`, the rotor length `L`, ...)
NEIGHBOURS: dict[str, dict[str, list[str]]] = {
    "lathe": {
        "T1": ["T2", "spindle@{here}"],
        "T2": ["T1", "spindle@{here}"],
        "T3": ["bed@{here+100}", "bed@{here-100}", "T6"],
        "T4": ["bed@{here+100}", "T3"],
        "T5": ["bed@{here-100}", "T3"],
        "T6": ["bed@{saddle}"],
    },
    "spindle": {
        "T_xi": ["housing@{here}", "rotor@{here+0.15L}", "rotor@{here-0.15L}"],
        "T_brg_front": ["rotor@{0}", "housing@{0.25L}"],
        "T_brg_rear": ["rotor@{L}", "housing@{0.75L}"],
        "T_coolant": ["housing@{0.5L}"],
    },
    "gantry": {
        f"T{i}{c}": nb
        for i in (1, 2)
        for c, nb in {
            "0": [f"T{i}2"],
            "1": [f"T{i}2"],
            "2": [f"T{i}3", f"T{i}0"],
            "3": [f"T{i}2"],
            "4": [f"T{i}2"],
            "A": [f"T{i}B", f"T{i}2"],
            "B": [f"T{i}A"],
            "C": [f"T{i}D", f"T{i}3"],
            "D": [f"T{i}C"],
        }.items()
    },
    "feed_axis": {
        "T_motor": ["T_table"],
        "T_table": ["T_head", "T_motor"],
        "T_head": ["T_table"],
        "T_block": ["T_table"],
        "T_base_*": ["y.base@{here+60}", "y.base@{here-60}"],
    },
    # the column's sensors see more of the column, never the spindle (each source its own sensors)
    "vmc": {
        "T_xi": ["housing@{here}", "rotor@{here+0.15L}", "rotor@{here-0.15L}"],
        "T_brg_front": ["rotor@{0}", "housing@{0.25L}"],
        "T_brg_rear": ["rotor@{L}", "housing@{0.75L}"],
        "T_coolant": ["housing@{0.5L}"],
        "T_col_top": ["column@{here-100}", "column@{H}"],
        "T_col_bot": ["column@{here+100}", "column@{0}"],
    },
}

# the two days. `level` is speed_rpm (lathe, spindle) or feed_mm_min (gantry, feed_axis).
DUTY: dict[str, dict[str, Any]] = {
    "lathe": {
        "train_level": ("uniform", 1200.0, 2800.0),
        "step": 100.0,
        "limits": (300.0, 4500.0),
        "train_run_s": ("uniform", 7200.0, 21600.0),
        "train_pause_s": ("uniform", 1800.0, 5400.0),
    },
    "spindle": {
        "train_level": ("uniform", 6000.0, 12000.0),
        "step": 500.0,
        "limits": (2000.0, 18000.0),
        "train_run_s": ("uniform", 3600.0, 10800.0),
        "train_pause_s": ("uniform", 1800.0, 3600.0),
        "coolant_p": 0.7,  # machines run with coolant on; on the unseen day some runs without
        "coolant_flip_p": 0.25,
    },
    "gantry": {
        "train_level": ("uniform", 800.0, 3000.0),
        "step": 100.0,
        "limits": (300.0, 6000.0),
        "train_run_s": ("uniform", 2700.0, 7200.0),
        "train_pause_s": ("uniform", 600.0, 2700.0),
    },
    "feed_axis": {
        "train_level": ("uniform", 3000.0, 9000.0),
        "step": 100.0,
        "limits": (1000.0, 15000.0),
        "train_run_s": ("uniform", 1800.0, 5400.0),
        "train_pause_s": ("uniform", 300.0, 1800.0),
    },
}
DUTY["vmc"] = dict(DUTY["spindle"])  # the same spindle, the same work
COMMON_DUTY = {
    "second_level_p": 0.5,  # share of training days at two levels
    "second_level": ("uniform", 0.6, 0.85),  # the second level as a share of the first, or the first of it
    "start_idle_s": ("uniform", 0.0, 3600.0),
    "unseen_start_idle_s": ("uniform", 0.0, 7200.0),
    "train_work_end_h": ("uniform", 12.0, 16.0),
    "unseen_work_end_h": ("uniform", 13.0, 18.0),
    "unseen_levels": (2, 4),  # how many levels the unseen day runs (one below, one above the training's)
    "below": ("uniform", 0.35, 0.85),  # a level below the training range, share of its lowest
    "above": ("uniform", 1.15, 1.6),  # a level above it, share of its highest
    "unseen_run_s": ("log", 1200.0, 10800.0),
    "unseen_pause_s": ("log", 300.0, 3600.0),
    "load": ("uniform", 0.8, 1.3),
    "round_s": 60.0,  # durations drawn to whole minutes
    # strokes (gantry, feed axis): the share of machines whose training day also has partial
    # strokes, the share of training runs that then are partial, the share of unseen runs
    # that are (the first always is), and how much of the travel a partial stroke covers
    "train_partial_machines_p": 0.5,
    "train_partial_runs_p": 0.4,
    "unseen_partial_runs_p": 0.8,
    "partial_share": ("uniform", 0.25, 0.6),
}

# the training day as compd testplan's plan (draw(train="plan")): the builder gives the type's speed
# range (lathe, spindle, vmc) or its axis with the drawn stroke and the type's feed range (gantry: the
# gantry's axis x, both sides; feed axis: y), the day's hours, and leaves compd's defaults (7 speed or
# 4 feed levels, τ 60 min, idle 1 h, a measurement every 10 min); the plan's seed is the machine's
PLAN = {
    "time_constant_min": 60.0,
    "probe_every_min": 10.0,
    "idle_hours": 1.0,
    "axis": {"gantry": "x", "feed_axis": "y"},
}
TRAINS = ("day", "plan")

AMBIENT = {
    "start_c": ("uniform", 18.0, 23.0),
    "drift_k_per_day": ("uniform", -1.0, 1.0),
    "daily_amplitude_c": ("uniform", 0.0, 1.0),
    "daily_phase_h": ("uniform", 0.0, 24.0),
    "hvac_amplitude_c": ("uniform", 0.1, 0.5),
    "hvac_period_s": ("uniform", 900.0, 3600.0),
    "hvac_shapes": ("sine", "square", "triangle"),
    "unseen_offset_c": ("uniform", 0.0, 2.0),  # the unseen day starts this much warmer or colder
}


# ======================================================================================
@dataclass
class Machine:
    """One drawn machine: its plant's params, its two days and what was drawn."""

    kind: str
    seed: int
    params: dict[str, Any]
    train: Scenario
    unseen: Scenario
    drawn: dict[str, Any]

    def plant(self, day: str) -> Any:
        """A fresh plant running `day` (train or unseen)."""
        from hil_sim.plants import PLANTS

        scenario = {"train": self.train, "unseen": self.unseen}[day]
        return PLANTS.get(self.kind)(scenario, self.params)

    def to_dict(self) -> dict[str, Any]:
        """The machine file's content: plain YAML types; `train` and `unseen` are scenarios."""
        return _plain(
            {
                "kind": self.kind,
                "seed": self.seed,
                "drawn": self.drawn,
                "params": self.params,
                "train": self.train.to_dict(),
                "unseen": self.unseen.to_dict(),
            }
        )


def draw(kind: str, seed: int, day_h: float = 24.0, train: str = "day") -> Machine:
    """Machine `seed` of the family `kind`: the same seed gives the same machine and days.

    `day_h` shortens both days (every duration scaled by day_h/24, all else the same
    draws): for quick tests. `train="plan"` makes the training day compd testplan's plan for
    the machine (PLAN), day_h long, in the drawn training day's ambient; everything else is
    drawn as for `train="day"`.
    """
    if train not in TRAINS:
        raise BadInput(f"unknown training day {train!r} (known: {', '.join(TRAINS)})", path="--train")
    if kind not in ALL_KINDS:
        raise BadInput(f"unknown kind {kind!r} (known: {', '.join(ALL_KINDS)})", path="--kind")
    if isinstance(seed, bool) or not isinstance(seed, int | np.integer) or seed < 0:
        raise BadInput(f"a seed is an integer >= 0, got {seed!r}", path="--seeds")
    if not day_h > 0:
        raise BadInput("day_h must be > 0")
    # one stream per aspect, so a new param in one table does not move the others' draws
    streams = np.random.SeedSequence([zlib.crc32(kind.encode()), int(seed)]).spawn(6)
    r_par, r_place, r_sens, r_train, r_unseen, r_amb = (np.random.default_rng(s) for s in streams)
    from hil_sim.plants import PLANTS

    defaults = {**PLANTS.get(kind).DEFAULTS}
    params: dict[str, Any] = {}
    factors: dict[str, float] = {}  # on the defaults
    values: dict[str, float] = {}  # drawn outright
    for name, spec in RANGES[kind].items():
        params[name], got = _draw_param(r_par, spec, defaults[name])
        (factors if spec[0] == "factor" else values)[name] = got
    drawn: dict[str, Any] = {"factors": factors, "values": values}
    places = _PLACE[kind](r_place, params, defaults)
    drawn["placement"] = places
    sensors = _sensors(r_sens, kind, params, places)
    drawn["sensors"] = sensors
    params["sensor_lag_s"] = sensors["lag_s"]
    if sensors["crosstalk"]:
        params["sensor_crosstalk"] = sensors["crosstalk"]
    train_amb, unseen_amb, amb_drawn = _ambients(r_amb)
    drawn["ambient"] = amb_drawn
    seeds = [int(s) for s in r_amb.integers(0, 2**31 - 1, 2)]  # the PT100 noise of each day
    travel = tuple(float(v) for v in params.get("stroke_mm", defaults.get("stroke_mm", [0.0, 0.0])))
    train_segs, unseen_segs, duty = _days(kind, r_train, r_unseen, params, travel)  # type: ignore[arg-type]
    drawn["duty"] = duty
    scale = day_h / 24.0
    if scale != 1.0:
        drawn["day_h"] = float(day_h)
        train_segs, unseen_segs = _scaled(train_segs, scale), _scaled(unseen_segs, scale)
    if train == "plan":
        train_segs, drawn["plan"] = _plan_day(kind, int(seed), params, travel, day_h)  # type: ignore[arg-type]
    train = Scenario(train_segs, train_amb, seeds[0], kind, params)
    unseen = Scenario(unseen_segs, unseen_amb, seeds[1], kind, params)
    return Machine(kind, int(seed), params, train, unseen, drawn)


# --------------------------------------------------------------------------------------
# drawing helpers
def _sig(x: float, digits: int = 4) -> float:
    """`x` to `digits` significant digits: the machine file then holds exactly what ran."""
    return float(f"{x:.{digits}g}")


def _value(r: np.random.Generator, spec: tuple[str, float, float]) -> float:
    how, lo, hi = spec
    if how == "uniform":
        return float(r.uniform(lo, hi))
    if how in ("log", "factor"):
        return float(math.exp(r.uniform(math.log(lo), math.log(hi))))
    raise ValueError(f"unknown draw {how!r}")


def _draw_param(r: np.random.Generator, spec: tuple[str, float, float], default: Any) -> tuple[Any, float]:
    """(the param's value, the factor on its default, or the value when the draw is absolute)."""
    if spec[0] != "factor":
        v = _sig(_value(r, spec))
        return v, v
    f = _value(r, spec)
    if isinstance(default, list):
        return [_sig(f * float(d)) for d in default], _sig(f)
    return _sig(f * float(default)), _sig(f)


def _round_to(x: float, step: float) -> float:
    """`x` to a multiple of `step` (with no float dust: 72.1, not 72.10000000000001)."""
    return round(float(step * round(x / step)), 9)


def _place_lathe(r: np.random.Generator, params: dict[str, Any], defaults: dict[str, Any]) -> dict[str, Any]:
    t = PLACEMENT["lathe"]
    lsp, lbed = params["spindle_length_mm"], params["bed_length_mm"]
    # nominal places scale with the drawn lengths: T1 near the nose, T2 near the rear bearing,
    # T3 mid-bed, T4 and T5 near its ends (the paper's Fig. 4)
    d_lsp, d_bed = defaults["spindle_length_mm"], defaults["bed_length_mm"]
    nominal = [x * (lsp / d_lsp if k < 2 else lbed / d_bed) for k, x in enumerate(defaults["sensor_x_mm"])]
    xs = []
    for k, x in enumerate(nominal):
        off = _value(r, t[f"T{k + 1}_mm"])
        top = lsp if k < 2 else lbed
        xs.append(_round_to(min(max(x + off, 0.02 * top), 0.98 * top), 1.0))
    params["sensor_x_mm"] = xs
    saddle = max(_value(r, t["saddle_at_bed_share"]) * lbed, lsp + 200.0)
    params["saddle_x_mm"] = _round_to(saddle, 10.0)
    return {"sensor_x_mm": xs, "saddle_x_mm": params["saddle_x_mm"]}


def _place_spindle(r: np.random.Generator, params: dict[str, Any], defaults: dict[str, Any]) -> dict[str, Any]:
    from hil_sim.plants.spindle import SpindlePlant

    # the mean-value point of this rotor's own steady field (the plant's, coolant off)
    xi_mm = SpindlePlant(Scenario([Segment(1.0)]), params).xi_mm
    length = params["length_mm"]
    share = _value(r, PLACEMENT["spindle"]["xi_offset_share"])
    at = _round_to(min(max(xi_mm + share * length, 0.05 * length), 0.95 * length), 0.1)
    params["xi_mm"] = at
    return {"xi_mean_value_point_mm": _sig(xi_mm), "xi_mm": at, "xi_offset_share": _sig(share, 3)}


def _place_gantry(r: np.random.Generator, params: dict[str, Any], defaults: dict[str, Any]) -> dict[str, Any]:
    t = PLACEMENT["gantry"]
    has = bool(r.uniform() < t["column_p"])
    draws = {k: _sig(_value(r, t[k])) for k in t if k != "column_p"}  # drawn always: stable streams
    if not has:
        return {"column": False}
    params.update(draws)
    return {"column": True, **draws}


def _place_feed_axis(r: np.random.Generator, params: dict[str, Any], defaults: dict[str, Any]) -> dict[str, Any]:
    t = PLACEMENT["feed_axis"]
    stroke = _round_to(_value(r, t["stroke_mm"]), 10.0)
    d_lo, d_hi = defaults["stroke_mm"]
    overhang = defaults["base_length_mm"] - (d_hi - d_lo)  # the default's base beyond the stroke
    base = stroke + overhang
    params["stroke_mm"] = [0.0, stroke]
    params["base_length_mm"] = base
    # the default's cell size (20 mm), so the rod resolves the same detail on any length
    params["base_nodes"] = int(round(base / (defaults["base_length_mm"] / defaults["base_nodes"])))
    nominal = [_round_to(stroke * k / 4.0, 10.0) for k in range(5)]
    shift = [_round_to(_value(r, t["base_sensor_mm"]), 1.0) for _ in nominal]
    x0 = defaults["stroke_offset_mm"]
    shift = [min(max(s, -(x0 + y)), base - (x0 + y)) for s, y in zip(shift, nominal, strict=True)]
    params["base_sensors_mm"] = nominal
    params["stroke_offset_mm"] = x0
    params["drift_sensor"] = f"T_base_{int(nominal[3]):03d}"  # the default's drifting one: ¾ of the stroke
    params["base_sensor_shift_mm"] = shift
    return {"stroke_mm": stroke, "base_length_mm": base, "base_sensors_mm": nominal, "base_sensor_shift_mm": shift}


def _place_vmc(r: np.random.Generator, params: dict[str, Any], defaults: dict[str, Any]) -> dict[str, Any]:
    from hil_sim.plants.vmc import VmcPlant

    t = PLACEMENT["vmc"]
    height = params["column_height_mm"]
    scale = height / defaults["column_height_mm"]
    params["headstock_at_mm"] = _round_to(defaults["headstock_at_mm"] * scale, 1.0)
    places: dict[str, Any] = {"headstock_at_mm": params["headstock_at_mm"]}
    for name, key in (("T_col_top", "column_top_sensor_mm"), ("T_col_bot", "column_bottom_sensor_mm")):
        at = defaults[key] * scale + _value(r, t[f"{name}_mm"])
        params[key] = places[key] = _round_to(min(max(at, 0.02 * height), 0.98 * height), 1.0)
    # the ξ sensor as the spindle's: off the mean-value point of this rotor's own steady field
    xi_mm = VmcPlant(Scenario([Segment(1.0)]), params).xi_mm
    length = params["length_mm"]
    share = _value(r, t["xi_offset_share"])
    params["xi_mm"] = _round_to(min(max(xi_mm + share * length, 0.05 * length), 0.95 * length), 0.1)
    return {
        **places,
        "xi_mean_value_point_mm": _sig(xi_mm),
        "xi_mm": params["xi_mm"],
        "xi_offset_share": _sig(share, 3),
    }


_PLACE = {
    "lathe": _place_lathe,
    "spindle": _place_spindle,
    "gantry": _place_gantry,
    "feed_axis": _place_feed_axis,
    "vmc": _place_vmc,
}


def _sensor_names(kind: str, params: dict[str, Any]) -> list[str]:
    if kind == "lathe":
        return [f"T{k}" for k in range(1, 8)]
    if kind == "spindle":
        return ["T_xi", "T_amb", "T_brg_front", "T_brg_rear", "T_coolant"]
    if kind == "vmc":
        return ["T_xi", "T_amb", "T_brg_front", "T_brg_rear", "T_coolant", "T_col_top", "T_col_bot"]
    if kind == "gantry":
        return ["T0"] + [f"T{i}{c}" for i in (1, 2) for c in "01234ABCD"]
    return (
        ["T_motor", "T_table", "T_head", "T_block"]
        + [f"T_base_{int(y):03d}" for y in params["base_sensors_mm"]]
        + ["T_amb"]
    )


def _here_mm(kind: str, sensor: str, params: dict[str, Any]) -> dict[str, float]:
    """The positions a NEIGHBOURS template may name for `sensor`."""
    if kind == "lathe":
        k = int(sensor[1:]) - 1
        here = params["sensor_x_mm"][k] if k < 5 else params["saddle_x_mm"]
        return {"here": here, "saddle": params["saddle_x_mm"]}
    if kind == "vmc" and sensor.startswith("T_col_"):
        key = "column_top_sensor_mm" if sensor == "T_col_top" else "column_bottom_sensor_mm"
        return {"here": params[key], "H": params["column_height_mm"]}
    if kind in ("spindle", "vmc"):
        return {"here": params["xi_mm"], "L": params["length_mm"]}
    if kind == "feed_axis" and sensor.startswith("T_base_"):
        k = params["base_sensors_mm"].index(float(sensor[7:]))
        return {"here": params["stroke_offset_mm"] + params["base_sensors_mm"][k] + params["base_sensor_shift_mm"][k]}
    return {}


_TERM = re.compile(r"([+-]?)(\d*\.?\d*)([A-Za-z_]*)")


def _fill(template: str, at: dict[str, float]) -> str:
    """`body@{here+100}` → `body@1100`: a NEIGHBOURS entry at the drawn places (a sum of
    terms, each a number, a name of `at`, or a number times a name: `0.25L`)."""
    if "{" not in template:
        return template
    head, expr = template.split("{", 1)
    total = 0.0
    for term in re.findall(r"[+-]?[^+-]+", expr.rstrip("}")):
        m = _TERM.fullmatch(term)
        if m is None:
            raise ValueError(f"neighbour template {template!r}: cannot read {term!r}")
        sign, num, name = m.groups()
        value = (float(num) if num else 1.0) * (at[name] if name else 1.0)
        total += -value if sign == "-" else value
    return f"{head}{_round_to(max(total, 0.0), 0.1):g}"


def _sensors(r: np.random.Generator, kind: str, params: dict[str, Any], places: dict[str, Any]) -> dict[str, Any]:
    names = _sensor_names(kind, params)
    lag = {}
    for n in names:
        spec = SENSORS["ambient_lag_s"] if n == AMBIENT_SENSOR[kind] else SENSORS["lag_s"]
        lag[n] = _sig(_value(r, spec), 3)
    crosstalk: dict[str, list[Any]] = {}
    table = NEIGHBOURS[kind]
    for n in names:
        # drawn for every sensor, kept or not, so the streams stay put
        keep, frac, pick = r.uniform(), _sig(_value(r, SENSORS["crosstalk"]), 3), r.uniform()
        options = table.get(n) or (table.get("T_base_*") if n.startswith("T_base_") else None)
        if not options or keep >= SENSORS["crosstalk_p"] or frac <= 0:
            continue
        crosstalk[n] = [frac, _fill(options[int(pick * len(options))], _here_mm(kind, n, params))]
    return {"lag_s": lag, "crosstalk": crosstalk}


def _ambients(r: np.random.Generator) -> tuple[Ambient, Ambient, dict[str, Any]]:
    t = AMBIENT
    out = []
    start = _sig(_value(r, t["start_c"]))
    offset = _sig(_value(r, t["unseen_offset_c"]) * (1.0 if r.uniform() < 0.5 else -1.0), 3)
    for day_start in (start, _sig(start + offset)):
        out.append(
            Ambient(
                start_c=day_start,
                drift_c_per_h=_sig(_value(r, t["drift_k_per_day"]) / 24.0, 3),
                daily_amplitude_c=_sig(_value(r, t["daily_amplitude_c"]), 3),
                daily_phase_h=_sig(_value(r, t["daily_phase_h"]), 3),
                hvac_amplitude_c=_sig(_value(r, t["hvac_amplitude_c"]), 3),
                hvac_period_s=_round_to(_value(r, t["hvac_period_s"]), 10.0),
                hvac_phase_s=_round_to(r.uniform(0.0, 3600.0), 10.0),
                hvac_shape=str(t["hvac_shapes"][int(r.integers(len(t["hvac_shapes"])))]),
            )
        )
    return out[0], out[1], {"train": out[0].to_dict(), "unseen": out[1].to_dict(), "unseen_offset_c": offset}


# --------------------------------------------------------------------------------------
# the days
def _dur(r: np.random.Generator, spec: tuple[str, float, float]) -> float:
    return max(COMMON_DUTY["round_s"], _round_to(_value(r, spec), COMMON_DUTY["round_s"]))


class _Day:
    """Segments of one day of one kind: runs at a level, pauses, and the night."""

    def __init__(self, kind: str, travel: tuple[float, float], r: np.random.Generator) -> None:
        self.kind, self.travel, self.r = kind, travel, r
        self.segments: list[Segment] = []
        self.t_s = 0.0
        self.axes = kind in ("gantry", "feed_axis")

    def run(
        self,
        duration_s: float,
        level: float,
        load: float = 1.0,
        stroke: tuple[float, float] | None = None,
        coolant: bool = False,
    ) -> None:
        if self.axes:
            seg = Segment(duration_s, feed_mm_min=level, load=load, stroke_mm=stroke or self.travel)
        else:
            seg = Segment(duration_s, speed_rpm=level, load=load, coolant=coolant)
        self.segments.append(seg)
        self.t_s += duration_s

    def pause(self, duration_s: float, coolant: bool = False) -> None:
        if self.axes:  # the axis stands somewhere on its travel
            lo, hi = self.travel
            seg = Segment(duration_s, pos_mm=_round_to(self.r.uniform(lo, hi), 10.0))
        else:
            seg = Segment(duration_s, coolant=coolant)
        self.segments.append(seg)
        self.t_s += duration_s

    def partial(self) -> tuple[float, float]:
        """A stroke over part of the travel, at one end."""
        lo, hi = self.travel
        share = _value(self.r, COMMON_DUTY["partial_share"])
        width = _round_to(share * (hi - lo), 10.0)
        return (lo, lo + width) if self.r.uniform() < 0.5 else (hi - width, hi)

    def night(self) -> None:
        """Standstill until the day's end (at least an hour: the cool-down)."""
        left = DAY_S - self.t_s
        if left > 0:
            self.pause(left)


def _levels(r: np.random.Generator, d: dict[str, Any]) -> list[float]:
    lo, hi = d["limits"]
    first = _round_to(_value(r, d["train_level"]), d["step"])
    if r.uniform() >= COMMON_DUTY["second_level_p"]:
        return [first]
    ratio = _value(r, COMMON_DUTY["second_level"])
    second = first * ratio if r.uniform() < 0.5 else first / ratio
    second = min(max(_round_to(second, d["step"]), lo), hi)
    return [first] if second == first else [first, second]


def _days(
    kind: str,
    r_train: np.random.Generator,
    r_unseen: np.random.Generator,
    params: dict[str, Any],
    travel: tuple[float, float],
) -> tuple[list[Segment], list[Segment], dict[str, Any]]:
    d, c = DUTY[kind], COMMON_DUTY
    lo_lim, hi_lim = d["limits"]
    levels = _levels(r_train, d)
    coolant = bool(r_train.uniform() < d.get("coolant_p", 0.0))
    partial_machine = bool(r_train.uniform() < c["train_partial_machines_p"])

    # training day: long runs at the training levels in turn, pauses, then the night
    day = _Day(kind, travel, r_train)
    day.pause(_dur(r_train, c["start_idle_s"]), coolant)
    end = _round_to(_value(r_train, c["train_work_end_h"]) * 3600.0, 60.0)
    k = 0
    while day.t_s < end - 600.0:
        run = min(_dur(r_train, d["train_run_s"]), end - day.t_s)
        partial = day.axes and partial_machine and r_train.uniform() < c["train_partial_runs_p"]
        day.run(run, levels[k % len(levels)], stroke=day.partial() if partial else None, coolant=coolant)
        k += 1
        if day.t_s < end - 600.0:
            day.pause(_dur(r_train, d["train_pause_s"]), coolant)
    day.night()
    train = day.segments

    # unseen day: one level below the training range, one above, others anywhere; runs,
    # pauses and loads of random size
    n_levels = int(r_unseen.integers(c["unseen_levels"][0], c["unseen_levels"][1] + 1))
    below = min(levels) * _value(r_unseen, c["below"])
    above = max(levels) * _value(r_unseen, c["above"])
    span = (min(levels) * c["below"][1], max(levels) * c["above"][2])
    unseen_levels = [min(max(_round_to(v, d["step"]), lo_lim), hi_lim) for v in (below, above)]
    while len(unseen_levels) < n_levels:  # the others anywhere, but not at a training level
        v = min(max(_round_to(r_unseen.uniform(*span), d["step"]), lo_lim), hi_lim)
        if v not in levels:
            unseen_levels.append(v)
    order = list(r_unseen.permutation(len(unseen_levels)))
    day = _Day(kind, travel, r_unseen)
    flip = d.get("coolant_flip_p", 0.0)
    day.pause(_dur(r_unseen, c["unseen_start_idle_s"]), coolant)
    end = _round_to(_value(r_unseen, c["unseen_work_end_h"]) * 3600.0, 60.0)
    k = 0
    while day.t_s < end - 600.0:
        run = min(_dur(r_unseen, c["unseen_run_s"]), end - day.t_s)
        level = unseen_levels[order[k]] if k < len(order) else unseen_levels[int(r_unseen.integers(len(unseen_levels)))]
        load = _sig(_value(r_unseen, c["load"]), 3)
        partial = day.axes and (k == 0 or r_unseen.uniform() < c["unseen_partial_runs_p"])
        cool = coolant != bool(r_unseen.uniform() < flip)
        day.run(run, level, load, stroke=day.partial() if partial else None, coolant=cool)
        k += 1
        if day.t_s < end - 600.0:
            day.pause(_dur(r_unseen, c["unseen_pause_s"]), coolant)
    day.night()
    duty = {
        "level": "feed_mm_min" if day.axes else "speed_rpm",
        "train_levels": levels,
        "unseen_levels": sorted(set(unseen_levels)),
        "train_runs": sum(s.speed_rpm > 0 or s.feed_mm_min > 0 for s in train),
        "unseen_runs": k,
    }
    if kind in ("spindle", "vmc"):
        duty["coolant"] = coolant
    if day.axes:
        duty["train_partial_strokes"] = sum(s.stroke_mm is not None and tuple(s.stroke_mm) != day.travel for s in train)
    return train, day.segments, duty


def _plan_day(
    kind: str, seed: int, params: dict[str, Any], travel: tuple[float, float], day_h: float
) -> tuple[list[Segment], dict[str, Any]]:
    """The training day as compd testplan designs it for this machine (PLAN), `day_h` hours; a
    shortened day scales τ, the idle stretch and the measuring interval with it."""
    lo, hi = DUTY[kind]["limits"]
    scale = day_h / 24.0
    step_s = max(1, round(PLAN["probe_every_min"] * 60.0 * scale))  # whole seconds, as the plan's times
    options = {
        "time_constant_min": _sig(PLAN["time_constant_min"] * scale, 6),
        "probe_every_min": step_s / 60.0,
        "idle_hours": _sig(PLAN["idle_hours"] * scale, 6),
        "seed": seed,
    }
    if kind in PLAN["axis"]:
        stroke = travel[1] - travel[0]
        # a shortened day's short steps: the lowest feed raised until one stroke out and back fits a step
        low = max(lo, math.ceil(2.0 * stroke * 60.0 / step_s))
        plan = design(0.0, day_h, axes=[Axis(PLAN["axis"][kind], stroke, hi, low)], **options)
    else:
        plan = design(hi, day_h, min_rpm=lo, **options)
    info = plan.info
    summary = {
        "max_rpm": hi if info["spindle"] else 0.0,
        "hours": float(day_h),
        **options,
        "levels": info["speeds_rpm"] or {a: f for a, f in info["feeds_mm_min"].items()},
        "holds": len(info["holds_s"]),
        "pauses": len(info["pauses_s"]),
        "probes": info["probes"],
    }
    return plan_segments(plan, stroke_mm=travel if kind in PLAN["axis"] else None), _plain(summary)


def _scaled(segments: list[Segment], scale: float) -> list[Segment]:
    """The day with every duration times `scale` (whole seconds, at least one)."""
    out = []
    for s in segments:
        out.append(
            Segment(
                **{**s.__dict__, "duration_s": max(1.0, round(s.duration_s * scale)), "axis_load": dict(s.axis_load)}
            )
        )
    return out


def _plain(x: Any) -> Any:
    """Plain Python types for YAML (numpy scalars and tuples converted)."""
    if isinstance(x, dict):
        return {str(k): _plain(v) for k, v in x.items()}
    if isinstance(x, list | tuple):
        return [_plain(v) for v in x]
    if isinstance(x, np.integer):
        return int(x)
    if isinstance(x, np.floating):
        return float(x)
    if isinstance(x, np.bool_):
        return bool(x)
    return x


# --------------------------------------------------------------------------------------
# files and the command
def working_rms_um(log_rows: np.ndarray, t_s: np.ndarray, scenario: Scenario) -> float:
    """RMS of an error column over the working part of a day (to the end of its last run)."""
    ends = scenario.boundaries()[1:]
    busy = [e for s, e in zip(scenario.segments, ends, strict=True) if s.speed_rpm > 0 or s.feed_mm_min > 0]
    last = busy[-1] if busy else scenario.duration_s
    v = log_rows[t_s <= last + 1e-9]
    return float(np.sqrt(np.mean(v**2))) if v.size else 0.0


def write_machine(machine: Machine, out_dir: str | Path, rate_s: float | None = None) -> dict[str, Any]:
    """Write the machine's two day logs and its machine file (what was drawn, the log period
    `log_rate_s` and the errors); return per day and axis the RMS and max |error| over the day
    and the RMS over its working part (µm)."""
    import yaml

    from hil_sim.logcmd import run_log

    out = Path(out_dir)
    rate = RATES_S[machine.kind] if rate_s is None else rate_s
    if not rate > 0:
        raise BadInput("--rate-s must be > 0")
    stem = out / f"{machine.kind}_{machine.seed}"
    summary: dict[str, Any] = {}
    for day in ("train", "unseen"):
        plant = machine.plant(day)
        path = Path(f"{stem}_{day}.csv")
        s = run_log(plant, path, rate)
        from compd.log import read_log

        log = read_log(path)
        sc = machine.train if day == "train" else machine.unseen
        summary[day] = {
            a: {
                "rms_um": _sig(v["rms_um"]),
                "max_abs_um": _sig(v["max_abs_um"]),
                "working_rms_um": _sig(working_rms_um(log.col(f"err_{a}_um"), log.t_s, sc)),
            }
            for a, v in s["axes"].items()
        }
    doc = {**machine.to_dict(), "log_rate_s": float(rate), "errors_um": _plain(summary)}
    try:
        Path(f"{stem}_machine.yaml").write_text(
            yaml.safe_dump(doc, sort_keys=False, default_flow_style=None, width=110), encoding="utf-8"
        )
    except OSError as e:
        raise BadInput(f"cannot write the machine file: {e.strerror or e}", file=f"{stem}_machine.yaml") from None
    return summary


def parse_seeds(text: str) -> list[int]:
    """`1-20`, `7`, `1,4,9-12` → the seeds, in order, each once (BadInput otherwise)."""
    out: list[int] = []
    for part in text.split(","):
        a, dash, b = part.strip().partition("-")
        try:
            lo = int(a)
            hi = int(b) if dash else lo
        except ValueError:
            raise BadInput(f"seeds are N, N-M or a comma list of those, got {text!r}", path="--seeds") from None
        if lo < 0 or hi < lo:
            raise BadInput(f"a seed range runs from a seed >= 0 up, got {part.strip()!r}", path="--seeds")
        if hi - lo > 100_000:
            raise BadInput(f"too many seeds in {part.strip()!r}", path="--seeds")
        out += [s for s in range(lo, hi + 1) if s not in out]
    return out


def add_parser(sub: Any) -> None:
    """Register the `family` subcommand on an argparse subparsers object."""
    p = sub.add_parser("family", help="draw machines of a randomized family and log their two days")
    p.add_argument("--kind", required=True, help=f"one of {', '.join(ALL_KINDS)}")
    p.add_argument("--seeds", required=True, help="e.g. 1-20, 7 or 1,4,9-12: one machine per seed")
    p.add_argument("--out", required=True, help="folder for the logs and machine files")
    p.add_argument(
        "--rate-s",
        type=float,
        default=None,
        help="seconds between log rows (default per kind: " + ", ".join(f"{k} {v:g}" for k, v in RATES_S.items()) + ")",
    )
    p.add_argument(
        "--train",
        choices=TRAINS,
        default="day",
        help="the training day: the drawn day (default), or compd testplan's plan for the machine",
    )
    p.set_defaults(func=cmd_family)


def cmd_family(args: argparse.Namespace) -> int:
    if args.kind not in ALL_KINDS:
        raise BadInput(f"unknown kind {args.kind!r} (known: {', '.join(ALL_KINDS)})", path="--kind")
    seeds = parse_seeds(args.seeds)
    if args.rate_s is not None and not args.rate_s > 0:
        raise BadInput("--rate-s must be > 0")
    out = Path(args.out)
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as e:
        raise BadInput(f"cannot create the folder: {e.strerror or e}", file=str(out)) from None
    for seed in seeds:
        m = draw(args.kind, seed, train=args.train)
        s = write_machine(m, out, args.rate_s)
        parts = [
            f"{day} "
            + ", ".join(f"{a} rms {v['rms_um']:.2f} um (working {v['working_rms_um']:.2f})" for a, v in axes.items())
            for day, axes in s.items()
        ]
        print(f"{out / f'{m.kind}_{seed}'}: " + "; ".join(parts), flush=True)
    return 0

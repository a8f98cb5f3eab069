"""`compd testplan`: the design's properties, the plan CSV, bad input, and the programs read back —
the LinuxCNC one through LinuxCNC's own interpreter (`rs274`), FANUC's and Siemens' by a parser here."""

from __future__ import annotations

import math
import re
import shlex
import shutil
import subprocess
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pytest

from compd.cli import main
from compd.commissioning import testplan as tp
from compd.core.errors import BadInput

ROOT = Path(__file__).resolve().parents[2]
PAGE = ROOT / "docs" / "testplan.md"


def speeds_of(plan: tp.Plan) -> list[tuple[float, float, float]]:
    """(t_s, duration_s, speed) of each stretch at one speed (rows merged by speed alone)."""
    out: list[tuple[float, float, float]] = []
    for i in range(len(plan) - 1):
        v, dur = float(plan.speed_rpm[i]), float(plan.t_s[i + 1] - plan.t_s[i])
        if out and out[-1][2] == v:
            out[-1] = (out[-1][0], out[-1][1] + dur, v)
        else:
            out.append((float(plan.t_s[i]), dur, v))
    return out


def running_holds(plan: tp.Plan) -> list[tuple[float, float, float, dict[str, float]]]:
    return [h for h in plan.holds() if h[2] > 0 or any(f > 0 for f in h[3].values())]


# --------------------------------------------------------------------------------------
# the design
def test_every_level_is_held_short_and_long_within_0_to_max():
    plan = tp.design(12000, 24)
    levels = plan.info["speeds_rpm"]
    assert levels[0] == 1200 and levels[-1] == 12000 and len(levels) == 7
    holds = running_holds(plan)
    assert len(holds) == 14
    by_level = {v: sorted(d for _, d, s, _ in holds if s == v) for v in levels}
    assert all(len(d) == 2 for d in by_level.values()), by_level  # each level twice
    tau_s = 3600.0
    durations = [d for _, d, _, _ in holds]
    assert min(durations) <= tau_s / 3 and max(durations) >= 2.5 * tau_s  # from ~τ/4 to several τ
    # no level is only short or only long: its two holds differ
    assert all(d[0] < d[1] for d in by_level.values())
    assert set(plan.speed_rpm) <= {0.0, *levels} and plan.speed_rpm.max() <= 12000
    assert plan.speed_rpm[-1] == 0 and plan.t_s[-1] == 24 * 3600  # the last row ends the plan, 24 h


def test_the_order_is_pseudo_random_up_and_down_and_reproducible(tmp_path):
    orders = []
    for seed in (0, 1, 2):
        plan = tp.design(8000, 24, seed=seed)
        seq = [s for _, _, s, _ in running_holds(plan)]
        steps = np.diff(seq)
        assert np.all(steps != 0)  # never the same level twice in a row
        assert np.sum(steps > 0) >= 3 and np.sum(steps < 0) >= 3  # up and down, not a staircase
        assert seq != sorted(seq) and seq != sorted(seq, reverse=True)
        orders.append(seq)
    assert orders[0] != orders[1] != orders[2]
    a, b = tmp_path / "a.csv", tmp_path / "b.csv"
    tp.design(8000, 24, seed=1).write_csv(a)
    tp.design(8000, 24, seed=1).write_csv(b)
    assert a.read_bytes() == b.read_bytes()


def test_idle_stretch_cool_down_pauses_and_a_measurement_every_n_minutes():
    plan = tp.design(10000, 24, idle_hours=1.5, probe_every_min=15, time_constant_min=45)
    holds = plan.holds()
    assert holds[0][:3] == (0.0, 5400.0, 0.0)  # the idle stretch: nothing turns for 1.5 h
    pauses = [d for _, d, s, _ in holds[1:] if s == 0]
    assert len(pauses) >= 4 and len(set(pauses)) >= 3  # several lengths
    assert max(pauses) >= 1.5 * 45 * 60  # one long enough to cool most of the way
    assert holds[-1][2] == 0 and holds[-1][1] == max(pauses)  # the plan ends cooling down
    np.testing.assert_array_equal(plan.probe_times_s(), np.arange(0.0, 24 * 3600 + 1, 900.0))
    # every change falls on a measurement (the step is the measuring interval)
    changes = [t for t, *_ in holds] + [plan.t_s[-1]]
    assert set(changes) <= set(plan.probe_times_s())


def test_a_finer_step_changes_between_measurements():
    plan = tp.design(10000, 12, probe_every_min=20, step_min=5, time_constant_min=30)
    np.testing.assert_array_equal(plan.probe_times_s(), np.arange(0.0, 12 * 3600 + 1, 1200.0))
    starts = np.array([t for t, *_ in plan.holds()])
    assert np.all(starts % 300 == 0) and np.any(starts % 1200 != 0)
    off_grid = plan.t_s % 1200 != 0
    assert off_grid.any() and not plan.probe[off_grid].any()  # those rows are changes, not measurements


@pytest.mark.parametrize("hours", [4.0, 7.5, 24.0, 30.0, 72.0])
def test_the_plan_fits_the_hours(hours):
    plan = tp.design(6000, hours)
    assert hours * 3600 - 600 < plan.duration_s <= hours * 3600
    assert len(running_holds(plan)) == 14 * plan.info["passes"]
    assert plan.info["passes"] == (4 if hours == 72 else 1)
    assert {s for _, _, s, _ in running_holds(plan)} == set(plan.info["speeds_rpm"])


def test_axes_have_their_own_feed_spectrum_one_axis_at_a_time():
    axes = [tp.parse_axis("x:800:12000"), tp.parse_axis("Z:400:6000:1000")]
    plan = tp.design(12000, 24, axes=axes, feed_levels=3)
    assert plan.columns == ["t_s", "speed_rpm", "feed_x_mm_min", "feed_z_mm_min", "probe"]
    holds = running_holds(plan)
    moving = [sum(f > 0 for f in h[3].values()) for h in holds]
    assert max(moving) == 1 and min(moving) == 0  # one axis at a time, and holds with both standing
    seen = {(a, f) for _, _, _, feeds in holds for a, f in feeds.items() if f > 0}
    assert seen == {("x", 1200.0), ("x", 6600.0), ("x", 12000.0), ("z", 1000.0), ("z", 3500.0), ("z", 6000.0)}
    # the feeds are not tied to the speeds: some feed level goes with more than one speed
    speeds_with = {}
    for _, _, s, feeds in holds:
        for a, f in feeds.items():
            speeds_with.setdefault((a, f), set()).add(s)
    assert max(len(v) for v in speeds_with.values()) >= 2
    assert plan.strokes_mm == {"x": 800.0, "z": 400.0}


def test_a_machine_without_a_spindle_has_the_feeds_as_its_spectrum():
    plan = tp.design(0, 12, axes=[tp.parse_axis("y:600:15000:1500")], feed_levels=4, time_constant_min=30)
    assert not plan.speed_rpm.any()
    holds = running_holds(plan)
    feeds = [h[3]["y"] for h in holds]
    n = plan.info["passes"]
    assert n == 2 and len(holds) == 8 * n and sorted(set(feeds)) == [1500.0, 6000.0, 10500.0, 15000.0]
    assert all(feeds.count(f) == 2 * n for f in set(feeds))


# --------------------------------------------------------------------------------------
# the command
def test_the_command_writes_the_plan_and_says_what_it_made(tmp_path, capsys):
    out = tmp_path / "plan.csv"
    assert main(["testplan", "--max-rpm", "12000", "--hours", "24", "--out", str(out)]) == 0
    printed = capsys.readouterr().out.splitlines()
    assert printed[0] == "compd testplan: 7 speeds 1200..12000 rpm"
    assert printed[1].startswith("compd testplan: 14 holds 20..") and "cool-down pauses" in printed[1]
    assert printed[2] == "compd testplan: 145 measurements every 10 min; 24.00 h"
    assert printed[3] == f"compd testplan: 145 rows -> {out}"
    lines = out.read_text().splitlines()
    assert lines[0] == "t_s,speed_rpm,probe" and lines[1] == "0,0,1" and lines[-1] == "86400,0,1"
    plan = tp.read_plan(out)
    assert len(plan) == 145 and plan.probe.all()


BAD = [
    (["--hours", "24"], "--max-rpm"),
    (["--max-rpm", "-5", "--hours", "24"], "--max-rpm: must be ≥ 0"),
    (["--max-rpm", "9000", "--hours", "0"], "--hours: must be > 0"),
    (["--max-rpm", "9000", "--hours", "nan"], "--hours: must be a finite number"),
    (
        ["--max-rpm", "9000", "--hours", "3"],
        "--hours: 3 h is too short for one pass over the 7 levels: it needs at least 4.00 h",
    ),
    (["--max-rpm", "9000", "--hours", "24", "--min-rpm", "9500"], "--min-rpm: must be below --max-rpm"),
    (["--max-rpm", "0", "--hours", "24"], "--max-rpm: 0 means no spindle"),
    (["--max-rpm", "9000", "--hours", "24", "--levels", "1"], "--levels: a whole number from 2 to 50"),
    (["--max-rpm", "9000", "--hours", "24", "--levels", "x"], "argument --levels: not a whole number"),
    (["--max-rpm", "5", "--hours", "24", "--levels", "9"], "--levels: 9 levels from 0.5 to 5 rpm"),
    (
        ["--max-rpm", "9000", "--hours", "24", "--probe-every-min", "15", "--step-min", "10"],
        "--probe-every-min: the probing interval (15 min) must be a whole number of steps (10 min)",
    ),
    (["--max-rpm", "9000", "--hours", "24", "--step-min", "0.001"], "--step-min: must be a whole number of seconds"),
    (
        ["--max-rpm", "9000", "--hours", "24", "--axis", "q:100:1000"],
        "--axis: the axis is one letter of X, Y, Z, U, V, W",
    ),
    (["--max-rpm", "9000", "--hours", "24", "--axis", "x:100"], "--axis: give NAME:STROKE_MM:MAX_FEED_MM_MIN"),
    (["--max-rpm", "9000", "--hours", "24", "--axis", "x:-100:1000"], "--axis: x: the stroke must be > 0"),
    (["--max-rpm", "9000", "--hours", "24", "--axis", "x:100:1000:2000"], "--axis: x: the min feed must be below"),
    (
        ["--max-rpm", "9000", "--hours", "24", "--axis", "x:100:1000", "--axis", "X:50:500"],
        "--axis: axis x given twice",
    ),
    (
        ["--max-rpm", "9000", "--hours", "24", "--axis", "x:2000:1000:50"],
        "--axis: x: one stroke out and back over 2000 mm at its lowest feed (50 mm/min) takes 4800 s",
    ),
    (["--max-rpm", "9000", "--hours", "24", "--gcode", "fanuc"], "--program: give --gcode and --program together"),
    (["--max-rpm", "9000", "--hours", "24", "--gcode", "heidenhain", "--program", "p"], "--gcode: invalid choice"),
    (
        ["--max-rpm", "9000", "--hours", "24", "--probe-call", "M98 P9001"],
        "--probe-call: the measuring call goes into a program",
    ),
    (
        ["--max-rpm", "9000", "--hours", "24", "--gcode", "fanuc", "--program", "p.nc", "--probe-call", "m98 p9001"],
        "--probe-call: a FANUC program is upper case",
    ),
    (["--max-rpm", "9000", "--hours", "24", "--seed", "-1"], "--seed: a whole number >= 0"),
    (
        ["--max-rpm", "9000", "--hours", "24", "--feed-levels", "30", "--axis", "x:100:1000"],
        "--feed-levels: 30 axis feeds and standing do not fit into the 14 holds of a pass",
    ),
    (
        ["--max-rpm", "9000", "--hours", "2000", "--step-min", "0.1"],
        "--hours: 2000 h in steps of 6 s are 1200000 steps",
    ),
]


@pytest.mark.parametrize("argv, says", BAD, ids=[b[1][:40] for b in BAD])
def test_bad_input_is_one_line_exit_2(argv, says, tmp_path, capsys):
    argv = [*argv, *([] if "--out" in argv else ["--out", str(tmp_path / "plan.csv")])]
    with pytest.raises(SystemExit) as e:
        raise SystemExit(main(["testplan", *argv]))
    assert e.value.code == 2
    err = capsys.readouterr().err
    assert len(err.strip().splitlines()) == 1 and says in err, err
    assert not (tmp_path / "plan.csv").exists()  # nothing written


def test_the_command_line_controls_are_the_generators():
    import argparse

    from compd.cli import build_parser

    sub = next(a for a in build_parser()._actions if isinstance(a, argparse._SubParsersAction)).choices["testplan"]
    gcode = next(a for a in sub._actions if a.dest == "gcode")
    assert tuple(gcode.choices) == tp.CONTROLLERS == tuple(tp.PROGRAMS)


# --------------------------------------------------------------------------------------
# reading a plan
def test_read_plan_round_trip(tmp_path):
    plan = tp.design(9000, 10, axes=[tp.parse_axis("y:500:9000")], time_constant_min=40)
    plan.write_csv(tmp_path / "p.csv")
    back = tp.read_plan(tmp_path / "p.csv")
    np.testing.assert_array_equal(back.t_s, plan.t_s)
    np.testing.assert_array_equal(back.speed_rpm, plan.speed_rpm)
    np.testing.assert_array_equal(back.feeds_mm_min["y"], plan.feeds_mm_min["y"])
    np.testing.assert_array_equal(back.probe, plan.probe)


@pytest.mark.parametrize(
    "text, says",
    [
        ("", "p.csv: the plan is empty"),
        ("t_s,probe\n0,1\n60,1\n", "p.csv:1: no column 'speed_rpm'"),
        ("t_s,speed_rpm\n0,100\n", "p.csv: a plan has at least two rows"),
        ("t_s,speed_rpm\n0,100\n60,x\n", "p.csv:3: speed_rpm: not a number: 'x'"),
        ("t_s,speed_rpm\n0,100\n60,-1\n", "p.csv:3: speed_rpm: must be >= 0"),
        ("t_s,speed_rpm\n0,100\n0,200\n", "p.csv:3: t_s: t_s must increase from row to row (0 after 0)"),
        ("t_s,speed_rpm,probe\n0,100,2\n60,0,1\n", "p.csv:2: probe: 0 or 1, got 2"),
        ("t_s,speed_rpm,feed_x_mm\n0,100,2\n60,0,1\n", "p.csv:1: feed_x_mm: a feed column is feed_<axis>_mm_min"),
        ("t_s,speed_rpm\n0,100\n60\n", "p.csv:3: row has 1 cells, the header has 2"),
        ("t_s,speed_rpm\n0,inf\n60,0\n", "p.csv:2: speed_rpm: not a finite number"),
    ],
)
def test_a_bad_plan_file_names_file_line_and_column(tmp_path, text, says):
    f = tmp_path / "p.csv"
    f.write_text(text)
    with pytest.raises(BadInput) as e:
        tp.read_plan(f)
    assert str(e.value).startswith(f"{tmp_path}/{says}"), str(e.value)


# --------------------------------------------------------------------------------------
# the programs read back
@dataclass
class Run:
    """What a program does, as an interpreter (or this test's parser) sees it."""

    t_s: float = 0.0
    speed: float = 0.0  # in force (0 while stopped)
    speeds: list[tuple[float, float]] = field(default_factory=list)  # (t, speed) at each change
    probes: list[float] = field(default_factory=list)
    moves: list[tuple[float, float, str, float, float]] = field(default_factory=list)  # (t0, t1, axis, mm, feed)
    dwells: list[float] = field(default_factory=list)

    def set_speed(self, v: float) -> None:
        if v != self.speed:
            self.speeds.append((self.t_s, v))
            self.speed = v

    def dwell(self, s: float) -> None:
        self.dwells.append(s)
        self.t_s += s

    def move(self, axis: str, mm: float, feed: float) -> None:
        dt = abs(mm) / feed * 60.0
        self.moves.append((self.t_s, self.t_s + dt, axis, mm, feed))
        self.t_s += dt


CANON = re.compile(r"^\s*\d+ N\.+ (\w+)\((.*)\)\s*$")
STUB = "compd-probe-stub"


def rs274_run(program: Path, call_name: str) -> Run:
    """The program through LinuxCNC's standalone interpreter, from its canonical calls."""
    exe = shutil.which("rs274")
    if exe is None:  # make test installs it (Makefile APT_PACKAGES_BARE): never skipped
        pytest.fail("rs274 is not installed (Debian package linuxcnc-uspace; `make sysdeps`)")
    # the user's measuring routine: a stub that leaves a mark in the canonical calls
    (program.parent / f"{call_name}.ngc").write_text(f"o<{call_name}> sub\n({STUB})\no<{call_name}> endsub\nM2\n")
    r = subprocess.run(
        [exe, "-g", program.name],
        cwd=program.parent,
        capture_output=True,
        text=True,
        timeout=120,
        stdin=subprocess.DEVNULL,
    )
    assert r.returncode == 0, r.stdout[-2000:] + r.stderr[-2000:]
    run, on, s, feed = Run(), False, 0.0, 0.0
    pos = np.zeros(9)
    letters = "xyzabcuvw"
    ended = False
    for line in r.stdout.splitlines():
        m = CANON.match(line)
        if not m:
            continue
        name, args = m[1], [a.strip() for a in m[2].split(",")]
        if name == "SET_SPINDLE_SPEED":
            s = float(args[1])
            if on:
                run.set_speed(s)
        elif name == "START_SPINDLE_CLOCKWISE":
            on = True
            run.set_speed(s)
        elif name in ("START_SPINDLE_COUNTERCLOCKWISE", "STRAIGHT_TRAVERSE", "ARC_FEED"):
            pytest.fail(f"the program does {name}: {line}")
        elif name == "STOP_SPINDLE_TURNING":
            on = False
            run.set_speed(0.0)
        elif name == "DWELL":
            run.dwell(float(args[0]))
        elif name == "SET_FEED_RATE":
            feed = float(args[0])
        elif name == "STRAIGHT_FEED":
            new = np.array([float(a) for a in args])
            delta = new - pos[: new.size]
            moved = np.flatnonzero(np.abs(delta) > 1e-9)
            assert moved.size == 1, line  # one axis at a time
            run.move(letters[moved[0]], float(delta[moved[0]]), feed)
            pos[: new.size] = new
        elif name == "COMMENT" and STUB in m[2]:
            run.probes.append(run.t_s)
        elif name == "PROGRAM_END":
            ended = True
    assert ended and run.speed == 0.0
    return run


def fanuc_run(text: str, call: str) -> Run:
    """A FANUC program as this test reads it: each block's words, custom-macro WHILE loops."""
    lines = text.splitlines()
    assert lines[0] == "%" and lines[-1] == "%" and re.fullmatch(r"O\d{4} \(.*\)", lines[1])
    assert lines[-2] == "M30"
    body = [ln for ln in lines[2:-1]]
    for ln in body:
        assert ln == ln.upper(), ln  # an ISO-code FANUC program is upper case
        assert ln.count("(") == ln.count(")") <= 1
    return _run_blocks([re.sub(r"\(.*\)", "", ln).strip() for ln in body], call, _fanuc_block)


def siemens_run(text: str, call: str) -> Run:
    lines = [ln.split(";", 1)[0].strip() for ln in text.splitlines()]
    assert [ln for ln in lines if ln][-1] == "M30"
    return _run_blocks(lines, call, _siemens_block)


def _run_blocks(blocks: list[str], call: str, block, run: Run | None = None, state: dict | None = None) -> Run:
    run = run or Run()
    state = state if state is not None else {"inc": False, "feed": None, "vars": {}, "s": None}
    k = 0
    while k < len(blocks):
        b = blocks[k]
        k += 1
        if not b:
            continue
        if b == call:
            run.probes.append(run.t_s)
            continue
        loop = re.fullmatch(r"WHILE \[#(\d+) LT (\d+)\] DO1|WHILE (R\d+)<(\d+)", b)
        if loop:
            var = f"#{loop[1]}" if loop[1] else loop[3]
            limit = int(loop[2] or loop[4])
            end = next(j for j in range(k, len(blocks)) if blocks[j] in ("END1", "ENDWHILE"))
            inner = blocks[k:end]
            while state["vars"][var] < limit:
                _run_blocks(inner, call, block, run, state)
            k = end + 1
            continue
        assign = re.fullmatch(r"(#\d+|R\d+)=(?:(\d+)|\1\+1)", b)
        if assign:
            state["vars"][assign[1]] = int(assign[2]) if assign[2] is not None else state["vars"][assign[1]] + 1
            continue
        block(b, run, state)
    return run


def _words(b: str) -> dict[str, str]:
    words = re.findall(r"([A-Z])(-?[0-9.]+)", b.replace(" ", ""))
    assert "".join(f"{a}{v}" for a, v in words) == b.replace(" ", ""), b
    out: dict[str, str] = {}
    for a, v in words:
        if a in ("G", "M"):
            out.setdefault(a, "")
            out[a] += f" {v}"
        else:
            assert a not in out, b
            out[a] = v
    return out


def _motion(w: dict[str, str], run: Run, state: dict, value) -> None:
    if "F" in w:
        state["feed"] = value(w["F"])
    for a in "XYZUVW":
        if a in w:
            assert state["inc"], "absolute moves: the program moves only incrementally"
            run.move(a.lower(), value(w[a]), state["feed"])


def _fanuc_block(b: str, run: Run, state: dict) -> None:
    w = _words(b)
    g = w.get("G", "").split()
    m = w.get("M", "").split()

    def dec(v: str) -> float:
        assert "." in v, f"{b}: a FANUC value without its decimal point reads in the least increment"
        return float(v)

    if "04" in g:
        assert set(w) == {"G", "X"} and g == ["04"], f"{b}: G04 alone in its block"
        assert 0 < dec(w["X"]) <= 9999.999
        run.dwell(dec(w["X"]))
        return
    if "91" in g:
        state["inc"] = True
    if "90" in g:
        state["inc"] = False
    if "S" in w:
        assert "." not in w["S"]
        state["s"] = float(w["S"])
    if "03" in m:
        run.set_speed(state["s"])
    if "05" in m:
        run.set_speed(0.0)
    _motion(w, run, state, dec)


def _siemens_block(b: str, run: Run, state: dict) -> None:
    w = _words(b)
    g = w.get("G", "").split()
    m = w.get("M", "").split()
    if "4" in g:
        assert set(w) == {"G", "F"} and g == ["4"], f"{b}: G4 alone in its block"
        assert 0 < float(w["F"]) <= 9999.999
        run.dwell(float(w["F"]))
        return
    if "91" in g:
        state["inc"] = True
    if "90" in g:
        state["inc"] = False
    if "S" in w:
        state["s"] = float(w["S"])
    if "3" in m:
        run.set_speed(state["s"])
    if "5" in m:
        run.set_speed(0.0)
    _motion(w, run, state, float)


def assert_runs_the_plan(run: Run, plan: tp.Plan) -> None:
    """The program's schedule is the plan's: the speed in force and the time between changes (dwells
    and moves at their feed) equal the plan's speeds and hold times to the program's resolution
    (0.5 ms per dwell rounded); a measurement at each of the plan's; each axis reciprocates at the
    plan's feed over its stroke within the rows that name that feed, for all but one round trip."""
    # the plan's changes of speed (the program starts stopped), the program's
    want = [(t, d, v) for k, (t, d, v) in enumerate(speeds_of(plan)) if k > 0 or v != 0]
    assert [v for _, v in run.speeds] == [v for *_, v in want]
    rounded = sum(1 for d in run.dwells if d != round(d))
    tol = 0.0005 * max(rounded, 1) + 1e-6
    got_t = [t for t, _ in run.speeds]
    np.testing.assert_allclose(got_t, [t for t, _, _ in want], atol=tol, rtol=0)
    for (_, d, _), start, end in zip(want, got_t, [*got_t[1:], run.t_s][: len(got_t)], strict=True):
        assert abs((end - start) - d) <= tol, (start, end, d)  # the hold's length
    assert abs(run.t_s - plan.duration_s) <= tol
    np.testing.assert_allclose(run.probes, plan.probe_times_s(), atol=tol, rtol=0)
    # the axes
    moved = {a: 0.0 for a in plan.feeds_mm_min}
    for i in range(len(plan) - 1):
        t0, t1 = plan.t_s[i], plan.t_s[i + 1]
        inside = [mv for mv in run.moves if t0 - tol <= mv[0] < t1 - tol]
        for a, f in plan.feeds_mm_min.items():
            mine = [mv for mv in inside if mv[2] == a]
            if f[i] == 0:
                assert not mine, (t0, a)
                continue
            assert all(mv[4] == f[i] and abs(abs(mv[3]) - plan.strokes_mm[a]) < 1e-6 for mv in mine)
            assert all(mv[1] <= t1 + tol for mv in mine)
            trip = 2 * plan.strokes_mm[a] / f[i] * 60
            assert sum(mv[1] - mv[0] for mv in mine) > (t1 - t0) - trip - tol
            assert sum(mv[3] for mv in mine) == pytest.approx(0.0, abs=1e-6)  # back where it started
            moved[a] += sum(mv[1] - mv[0] for mv in mine)
    assert all(v > 0 for v in moved.values())


PLANS = {  # (design arguments, the LinuxCNC call)
    "spindle_24h": (dict(max_rpm=12000, hours=24), "o<probe> call"),
    "spindle_short": (
        dict(max_rpm=3000, hours=4.5, levels=4, probe_every_min=5, time_constant_min=20, idle_hours=0.5, seed=3),
        "o<probe> call",
    ),
    "spindle_long_finer_steps": (
        dict(max_rpm=18000, min_rpm=2000, hours=60, step_min=5, probe_every_min=15),
        "o<measure> call [1]",
    ),
    "spindle_with_axes": (
        dict(
            max_rpm=10000,
            hours=8,
            time_constant_min=30,
            axes=[tp.parse_axis("x:700:9000"), tp.parse_axis("z:235.5:4000")],
            feed_levels=3,
        ),
        "o<probe> call",
    ),
    "axes_only": (
        dict(max_rpm=0, hours=6, time_constant_min=20, axes=[tp.parse_axis("y:600:15000:1000")]),
        "o<probe> call",
    ),
}


def _plan(name: str) -> tuple[tp.Plan, str]:
    kwargs, call = PLANS[name]
    kw = dict(kwargs)
    return tp.design(kw.pop("max_rpm"), kw.pop("hours"), **kw), call


@pytest.mark.parametrize("name", list(PLANS))
def test_the_linuxcnc_program_reads_back_through_rs274_into_the_plan(name, tmp_path):
    plan, call = _plan(name)
    program = tmp_path / "plan.ngc"
    program.write_text(tp.linuxcnc(plan, call, "plan.csv"))
    run = rs274_run(program, re.match(r"o<(\w+)>", call)[1])
    assert_runs_the_plan(run, plan)
    assert len(run.probes) == int(plan.probe.sum()) > 10


@pytest.mark.parametrize("controller", ["fanuc", "siemens"])
@pytest.mark.parametrize("name", list(PLANS))
def test_the_fanuc_and_siemens_programs_encode_the_plan(name, controller):
    plan, _ = _plan(name)
    call = tp.PROBE_CALLS[controller]
    text = tp.PROGRAMS[controller](plan, call, "plan.csv")
    run = (fanuc_run if controller == "fanuc" else siemens_run)(text, call)
    assert_runs_the_plan(run, plan)


def test_a_dwell_longer_than_one_g04_takes_is_split():
    plan = tp.Plan(np.array([0.0, 25000.0, 25060.0]), np.array([5000.0, 0.0, 0.0]), {}, np.array([True, True, False]))
    for controller in ("fanuc", "siemens"):
        text = tp.PROGRAMS[controller](plan, tp.PROBE_CALLS[controller], "p.csv")
        run = (fanuc_run if controller == "fanuc" else siemens_run)(text, tp.PROBE_CALLS[controller])
        assert run.dwells == [9999.999, 9999.999, 5000.002, 60.0]
        assert_runs_the_plan(run, plan)
    assert "G4 P25000\n" in tp.linuxcnc(plan, "o<probe> call", "p.csv")


def test_the_program_header_says_what_made_it(tmp_path, capsys):
    from compd import version

    out, prog = tmp_path / "plan.csv", tmp_path / "O2303.nc"
    assert (
        main(
            [
                "testplan",
                "--max-rpm",
                "4500",
                "--hours",
                "24",
                "--axis",
                "z:600:8000",
                "--out",
                str(out),
                "--gcode",
                "fanuc",
                "--program",
                str(prog),
                "--probe-call",
                "M98 P9010",
            ]
        )
        == 0
    )
    said = capsys.readouterr().out.splitlines()[-1]
    assert said == f"compd testplan: 145 rows -> {out}; fanuc program -> {prog} (measuring call: M98 P9010)"
    text = prog.read_text()
    assert f"(COMPD {version()} TESTPLAN - THE THERMAL TEST FOR FANUC, FROM PLAN.CSV)" in text
    assert "(MEASURING CALL - M98 P9010 [A PLACEHOLDER FOR YOUR OWN PROBING ROUTINE])" in text
    assert "(AXES - START EACH AT THE LOW END OF ITS STROKE - IT MOVES + AND BACK, Z 600 MM)" in text
    assert text.count("M98 P9010") == 145 + 1


# --------------------------------------------------------------------------------------
# the page
def test_the_pages_commands_run_and_print_what_it_shows(tmp_path, monkeypatch, capsys):
    """docs/testplan.md: each `$ compd ...` line of its console blocks runs here and prints the lines shown
    (exit 0, or 2 where what it shows is compd's one-line error)."""
    monkeypatch.chdir(tmp_path)
    text = PAGE.read_text(encoding="utf-8")
    ran = 0
    for block in re.findall(r"```console\n(.*?)```", text, re.S):
        cmds: list[tuple[str, list[str]]] = []
        for line in block.splitlines():
            if line.startswith("$ "):
                cmds.append((line[2:], []))
            elif line.strip():
                cmds[-1][1].append(line)
        for cmd, shown in cmds:
            argv = shlex.split(cmd)
            assert argv[0] == "compd", cmd
            rc = main(argv[1:])
            assert rc == (2 if any(s.startswith("compd: ") for s in shown) else 0), cmd
            said = capsys.readouterr()
            printed = (said.out + said.err).splitlines()
            for s in shown:
                assert s in printed, (cmd, s, printed)
            ran += 1
    assert ran >= 4


def test_holds_are_whole_steps_summing_to_the_budget():
    x = np.array([0.2, 1.4, 2.6, 7.9])
    out = tp._apportion(x, 13)
    assert out.sum() == 13 and out.min() >= 1
    assert list(tp._apportion(np.array([0.1, 0.1, 0.1]), 3)) == [1, 1, 1]
    assert math.isclose(sum(tp._apportion(np.geomspace(0.25, 3, 14) * 6, 60)), 60)

"""`python -m hil_sim log`: log CSV round trip, sweeps, and bad input (exit 2)."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from compd.log import read_log
from hil_sim.__main__ import main

ROOT = Path(__file__).resolve().parents[2]
SCENARIOS = ROOT / "hil_sim" / "scenarios"


@pytest.mark.parametrize("machine", ["lathe", "spindle", "gantry", "feed_axis"])
def test_log_round_trip(machine, tmp_path, capsys):
    out = tmp_path / "log.csv"
    rc = main(
        [
            "log",
            "--scenario",
            str(SCENARIOS / f"{machine}_train.yaml"),
            "--out",
            str(out),
            "--duration-s",
            "1800",
            "--rate-s",
            "10",
        ]
    )
    assert rc == 0
    assert "181 rows" in capsys.readouterr().out
    log = read_log(out)
    assert len(log) == 181
    np.testing.assert_allclose(np.diff(log.t_s), 10.0)
    assert log.columns[0] == "t_s"
    assert log.error_columns()
    temps = log.temperature_columns()
    assert temps and all(10.0 < log.col(c).min() < 40.0 for c in temps)
    assert np.allclose(log.matrix(temps) * 10, np.round(log.matrix(temps) * 10), atol=1e-6)


def test_seed_makes_the_log_reproducible(tmp_path):
    f = str(SCENARIOS / "lathe_unseen.yaml")
    a, b, c = (tmp_path / n for n in ("a.csv", "b.csv", "c.csv"))
    for out, seed in ((a, "5"), (b, "5"), (c, "6")):
        main(["log", "--scenario", f, "--out", str(out), "--duration-s", "600", "--rate-s", "60", "--seed", seed])
    assert a.read_text() == b.read_text()
    assert a.read_text() != c.read_text()


def test_profile_sweeps_are_a_valid_log(tmp_path):
    out, prof = tmp_path / "log.csv", tmp_path / "prof.csv"
    rc = main(
        [
            "log",
            "--scenario",
            str(SCENARIOS / "feed_axis_train.yaml"),
            "--out",
            str(out),
            "--duration-s",
            "3600",
            "--rate-s",
            "30",
            "--profile",
            str(prof),
            "--profile-every-s",
            "1200",
        ]
    )
    assert rc == 0
    p = read_log(prof)
    assert len(p) == 4 * 31  # sweeps at 0, 1200, 2400, 3600 s over 0..600 mm
    last = p.data[p.t_s == 3600.0]
    np.testing.assert_allclose(last[:, p.index("pos_y_mm")], np.arange(0, 601, 20))
    assert np.ptp(last[:, p.index("err_y_um")]) > 0.1


def _run_bad(tmp_path, capsys, text: str) -> str:
    f = tmp_path / "bad.yaml"
    f.write_text(text, encoding="utf-8")
    rc = main(["log", "--scenario", str(f), "--out", str(tmp_path / "x.csv")])
    assert rc == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "bad.yaml" in err
    return err


def test_bad_scenarios_exit_2_with_one_line(tmp_path, capsys):
    assert "segments[0].sped_rpm" in _run_bad(
        tmp_path, capsys, "machine: lathe\nsegments:\n  - {duration_s: 5, sped_rpm: 3}\n"
    )
    assert "machine" in _run_bad(tmp_path, capsys, "segments:\n  - {duration_s: 5}\n")
    assert "not valid YAML" in _run_bad(tmp_path, capsys, "machine: lathe\nsegments: [\n")
    assert "bogus" in _run_bad(tmp_path, capsys, "machine: lathe\nparams: {bogus: 1}\nsegments:\n  - {duration_s: 5}\n")


def test_unknown_machine_and_missing_file(tmp_path, capsys):
    f = tmp_path / "m.yaml"
    f.write_text("machine: boat\nsegments:\n  - {duration_s: 5}\n", encoding="utf-8")
    assert main(["log", "--scenario", str(f), "--out", str(tmp_path / "x.csv")]) == 2
    assert "boat" in capsys.readouterr().err
    assert main(["log", "--scenario", str(tmp_path / "none.yaml"), "--out", "x.csv"]) == 2
    assert "none.yaml" in capsys.readouterr().err


def test_module_entry_point(tmp_path):
    out = tmp_path / "log.csv"
    r = subprocess.run(
        [
            sys.executable,
            "-m",
            "hil_sim",
            "log",
            "--scenario",
            str(SCENARIOS / "spindle_train.yaml"),
            "--out",
            str(out),
            "--duration-s",
            "120",
        ],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert r.returncode == 0, r.stderr
    assert read_log(out).columns[1:] == [
        "T_xi",
        "T_amb",
        "T_brg_front",
        "T_brg_rear",
        "T_coolant",
        "speed_rpm",
        "err_z_um",
        "err_radial_um",
    ]


# --- a compd testplan plan instead of the scenario's segments ----------------------------
def _plan_file(tmp_path: Path, **kw) -> tuple[Path, object]:
    from compd.commissioning.testplan import design

    max_rpm, hours = kw.pop("max_rpm"), kw.pop("hours")
    plan = design(max_rpm, hours, **kw)
    f = tmp_path / "plan.csv"
    plan.write_csv(f)
    return f, plan


def test_a_plan_drives_the_spindle_and_its_measurements_are_probes(tmp_path, capsys):
    f, plan = _plan_file(
        tmp_path, max_rpm=15000, hours=4.5, levels=4, probe_every_min=5, time_constant_min=20, idle_hours=0.5
    )
    out = tmp_path / "log.csv"
    assert (
        main(
            [
                "log",
                "--scenario",
                str(SCENARIOS / "spindle_train.yaml"),
                "--plan",
                str(f),
                "--out",
                str(out),
                "--rate-s",
                "120",
            ]
        )
        == 0
    )
    assert f"plan {f}: 55 probes" in capsys.readouterr().out
    log = read_log(out, allow_nan=True)
    assert log.t_s[-1] == plan.t_s[-1] == 4.5 * 3600
    # the speed in force at every row is the plan's row's from its t_s on
    k = np.searchsorted(plan.t_s, log.t_s, side="right") - 1
    np.testing.assert_array_equal(log.col("speed_rpm")[:-1], plan.speed_rpm[k][:-1])
    assert set(np.unique(log.col("speed_rpm"))) == {0.0, *plan.info["speeds_rpm"]}
    for axis in ("z", "radial"):
        z = log.col(f"probe_{axis}_um")
        at = np.isfinite(z)
        np.testing.assert_array_equal(log.t_s[at], plan.probe_times_s())  # every measurement, and only those
        miss = z[at] - log.col(f"err_{axis}_um")[at]
        assert np.all(np.abs(miss) < 5 * 0.3) and np.std(miss) > 0.1  # the true error plus the probe's noise
    assert np.ptp(log.col("err_z_um")) > 5.0  # the plan warms the machine


def test_a_plan_with_a_feed_moves_the_linear_axes_over_the_stroke(tmp_path):
    from compd.commissioning.testplan import parse_axis

    f, plan = _plan_file(tmp_path, max_rpm=0, hours=6, axes=[parse_axis("y:400:12000:1200")], time_constant_min=20)
    out = tmp_path / "log.csv"
    assert (
        main(
            [
                "log",
                "--scenario",
                str(SCENARIOS / "feed_axis_train.yaml"),
                "--plan",
                str(f),
                "--out",
                str(out),
                "--rate-s",
                "7",
                "--stroke-mm",
                "100",
                "500",
                "--probe-sigma-um",
                "0",
            ]
        )
        == 0
    )
    log = read_log(out, allow_nan=True)
    feed = plan.feeds_mm_min["y"][np.searchsorted(plan.t_s, log.t_s, side="right") - 1]
    pos = log.col("pos_y_mm")
    moving = feed > 0
    inside = np.r_[False, moving[1:] & moving[:-1]]  # a hold's first row: the axis is where it stood
    assert 100.0 <= pos[inside].min() < 150.0 and 450.0 < pos[inside].max() <= 500.0
    # standing: the axis stays where the last feed hold left it, row after row
    still = ~moving[1:] & ~moving[:-1]
    assert np.all(np.diff(pos)[still] == 0.0)
    at = np.isfinite(log.col("probe_y_um"))
    np.testing.assert_array_equal(log.t_s[at], plan.probe_times_s())
    np.testing.assert_array_equal(log.col("probe_y_um")[at], log.col("err_y_um")[at])  # σ 0: the error itself
    np.testing.assert_array_equal(log.col("probe_pos_y_mm")[at], pos[at])


@pytest.mark.parametrize(
    "extra, says",
    [
        (["--plan-axis", "x"], "--plan-axis: the plan has no feed_x_mm_min (its feed columns: none)"),
        (["--stroke-mm", "0", "100"], "--plan: --plan-axis and --stroke-mm go with --plan"),
        (["--probe-sigma-um", "-1"], "--probe-sigma-um must be >= 0"),
    ],
)
def test_plan_options_bad_input_one_line_exit_2(extra, says, tmp_path, capsys):
    f, _ = _plan_file(tmp_path, max_rpm=6000, hours=5)
    argv = ["log", "--scenario", str(SCENARIOS / "lathe_train.yaml"), "--out", str(tmp_path / "x.csv"), *extra]
    if "--stroke-mm" not in extra:
        argv += ["--plan", str(f)]
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and says in err, err


def test_a_plan_the_plant_cannot_follow_or_a_bad_plan_file_exit_2(tmp_path, capsys):
    f, _ = _plan_file(tmp_path, max_rpm=6000, hours=5)
    assert (
        main(
            [
                "log",
                "--scenario",
                str(SCENARIOS / "feed_axis_train.yaml"),
                "--plan",
                str(f),
                "--out",
                str(tmp_path / "x.csv"),
            ]
        )
        == 2
    )
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "the feed_axis plant follows nothing this plan changes" in err
    f.write_text("t_s,speed_rpm,probe\n0,100,1\n0,0,1\n")
    assert (
        main(
            [
                "log",
                "--scenario",
                str(SCENARIOS / "lathe_train.yaml"),
                "--plan",
                str(f),
                "--out",
                str(tmp_path / "x.csv"),
            ]
        )
        == 2
    )
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and f"{f}:3: t_s: t_s must increase" in err
    assert not (tmp_path / "x.csv").exists()

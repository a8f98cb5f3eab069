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
    rc = main(["log", "--scenario", str(SCENARIOS / f"{machine}_train.yaml"), "--out", str(out),
               "--duration-s", "1800", "--rate-s", "10"])
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
        main(["log", "--scenario", f, "--out", str(out), "--duration-s", "600", "--rate-s", "60",
              "--seed", seed])
    assert a.read_text() == b.read_text()
    assert a.read_text() != c.read_text()


def test_profile_sweeps_are_a_valid_log(tmp_path):
    out, prof = tmp_path / "log.csv", tmp_path / "prof.csv"
    rc = main(["log", "--scenario", str(SCENARIOS / "feed_axis_train.yaml"), "--out", str(out),
               "--duration-s", "3600", "--rate-s", "30", "--profile", str(prof),
               "--profile-every-s", "1200"])
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
        tmp_path, capsys, "machine: lathe\nsegments:\n  - {duration_s: 5, sped_rpm: 3}\n")
    assert "machine" in _run_bad(tmp_path, capsys, "segments:\n  - {duration_s: 5}\n")
    assert "not valid YAML" in _run_bad(tmp_path, capsys, "machine: lathe\nsegments: [\n")
    assert "bogus" in _run_bad(
        tmp_path, capsys, "machine: lathe\nparams: {bogus: 1}\nsegments:\n  - {duration_s: 5}\n")


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
        [sys.executable, "-m", "hil_sim", "log", "--scenario", str(SCENARIOS / "spindle_train.yaml"),
         "--out", str(out), "--duration-s", "120"],
        cwd=ROOT, capture_output=True, text=True, timeout=60,
    )
    assert r.returncode == 0, r.stderr
    assert read_log(out).columns[1:] == [
        "T_xi", "T_amb", "T_brg_front", "T_brg_rear", "T_coolant", "speed_rpm", "err_z_um",
        "err_radial_um",
    ]

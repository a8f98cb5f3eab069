"""Walks docs/commissioning.md on hil_sim, from an empty folder to a compensated machine.

The configs are the guide's own blocks (`<!-- file: NAME -->`), and every command run
here must appear in the guide as written. The one step the guide leaves to the machine,
a second day's log to compare models on, comes from `python -m hil_sim log`.
"""

from __future__ import annotations

import csv
import json
import os
import re
import subprocess
import sys
import time
import urllib.request
from pathlib import Path

import pytest

from compd.cli import main

ROOT = Path(__file__).resolve().parent.parent
GUIDE = ROOT / "docs" / "commissioning.md"


def guide_files() -> dict[str, str]:
    text = GUIDE.read_text(encoding="utf-8")
    return dict(re.findall(r"<!-- file: (\S+) -->\n```yaml\n(.*?)```", text, re.S))


def in_guide(command: str) -> str:
    assert f"$ {command}\n" in GUIDE.read_text(encoding="utf-8"), f"not in the guide: {command}"
    return command


def compd(command: str, cwd: Path, **kw) -> subprocess.CompletedProcess:
    """Run a guide command line (`compd ...`) as a process, in this checkout."""
    argv = [sys.executable, "-m", "compd", *in_guide(command).split()[1:]]
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    return subprocess.run(argv, cwd=cwd, env=env, capture_output=True, text=True, timeout=120, **kw)


def cli(command: str, capsys) -> tuple[int, str, str]:
    """Run a guide command line in process (fast: used while the daemon runs)."""
    rc = main(in_guide(command).split()[1:])
    out, err = capsys.readouterr()
    return rc, out, err


def read_csv(path: Path) -> dict[str, list[float]]:
    with open(path, newline="") as fh:
        rows = list(csv.reader(fh))
    return {name: [float(r[i]) for r in rows[1:]] for i, name in enumerate(rows[0])}


def wait_for_status(path: Path, pid: int, proc: subprocess.Popen, timeout_s: float = 60) -> dict:
    end = time.monotonic() + timeout_s
    while time.monotonic() < end:
        assert proc.poll() is None, proc.communicate()
        try:
            data = json.loads(path.read_text())
            if data["pid"] == pid and data["state"] == "running" and data["loop"]["cycles"] > 0:
                return data
        except (OSError, ValueError, KeyError):
            pass
        time.sleep(0.02)
    raise AssertionError("the daemon never reported running")


@pytest.mark.slow
def test_commissioning_walk(tmp_path, capsys, monkeypatch):
    monkeypatch.chdir(tmp_path)  # an empty folder
    assert list(tmp_path.iterdir()) == []
    files = guide_files()

    # 1. wire the sensors: the observe-mode config, checked
    (tmp_path / "machine.yaml").write_text(files["machine.yaml"])
    assert cli("compd check-config machine.yaml", capsys)[:2] == (0, "ok\n")

    # 2. a warm-up day in observe mode
    r = compd("compd run machine.yaml", tmp_path)
    assert r.returncode == 0, r.stderr
    assert "observe mode: the output was held disabled" in r.stdout
    summary = re.search(r"RMS error without compensation ([\d.]+) um, with ([\d.]+) um", r.stdout)
    assert summary and summary[1] == summary[2] and float(summary[1]) > 5.0
    assert "level=info event=start" in r.stderr and "observe=True" in r.stderr
    log = read_csv(tmp_path / "warmup.csv")
    assert {"t_s", "T_xi", "T_amb", "speed_rpm", "err_z_um", "pred_z_um", "applied_z_um", "word"} <= set(log)
    assert set(log["applied_z_um"]) == {0.0}, "observe mode applied a correction"
    assert max(log["pred_z_um"]) > 10.0 and max(log["err_z_um"]) > 10.0
    assert max(log["word"]) > 0  # the loop did compute words: they were held back
    assert log["t_s"][-1] >= 14000
    rc, out, err = cli("compd status --config machine.yaml", capsys)
    assert rc == 1 and "stopped" in err  # the run is over; its last status stays readable
    assert "OBSERVE MODE" in out and "(on the output: 0x0000)" in out

    # 3. fit the model on the warm-up log
    r = compd("compd fit --kind xi_spindle --log warmup.csv --inputs T_xi --target err_z_um --out model.yaml --report fit.json", tmp_path)
    assert r.returncode == 0, r.stderr
    import yaml

    model = yaml.safe_load((tmp_path / "model.yaml").read_text())
    assert model["kind"] == "xi_spindle" and model["inputs"] == ["T_xi"] and model["outputs"] == ["z"]
    assert model["fit"]["rows"] == len(log["t_s"])
    fit_rmse = model["fit"]["rmse_um"]["z"]
    assert 0 < fit_rmse < 1.5
    fit_report = json.loads((tmp_path / "fit.json").read_text())
    assert fit_report["axes"]["z"]["rmse_um"] == pytest.approx(fit_rmse)

    # 4. compare models: the baseline on the same log, and both on an unseen day.
    #    On hil_sim, "another day on the machine" is a day the simulator logs:
    day2 = subprocess.run(
        [sys.executable, "-m", "hil_sim", "log", "--scenario", str(ROOT / "hil_sim/scenarios/spindle_unseen.yaml"),
         "--out", "day2.csv", "--rate-s", "30", "--duration-s", "14400"],
        cwd=tmp_path, env={**os.environ, "PYTHONPATH": str(ROOT)}, capture_output=True, text=True, timeout=120,
    )
    assert day2.returncode == 0, day2.stderr
    r = compd("compd fit --kind mlr --log warmup.csv --inputs T_xi T_amb --target err_z_um --out mlr.yaml --report mlr.json", tmp_path)
    assert r.returncode == 0, r.stderr
    mlr_report = json.loads((tmp_path / "mlr.json").read_text())
    assert mlr_report["axes"]["z"]["rmse_um"] > 0
    r = compd("compd predict model.yaml --log day2.csv --out pred.csv", tmp_path)
    assert r.returncode == 0, r.stderr
    pred, unseen = read_csv(tmp_path / "pred.csv"), read_csv(tmp_path / "day2.csv")
    assert list(pred) == ["t_s", "pred_z_um"] and pred["t_s"] == unseen["t_s"]
    resid = [p - e for p, e in zip(pred["pred_z_um"], unseen["err_z_um"], strict=True)]
    rms_err = (sum(e * e for e in unseen["err_z_um"]) / len(resid)) ** 0.5
    rms_resid = (sum(x * x for x in resid) / len(resid)) ** 0.5
    assert rms_resid < 0.5 * rms_err  # the physics model carries over to a day it has not seen

    # 5. replay the warm-up log through the enabling config against the software PLC
    (tmp_path / "compensate.yaml").write_text(files["compensate.yaml"])
    r = compd("compd replay compensate.yaml --log warmup.csv --report replay.json", tmp_path)
    assert r.returncode == 0, r.stderr
    rep = json.loads((tmp_path / "replay.json").read_text())
    assert rep["rows"] == len(log["t_s"]) and rep["codes_sent"] > 5
    assert rep["axes"]["z"]["reduction_pct"] > 70 and rep["saturated"] == 0
    assert rep["axes"]["z"]["rms_before_um"] == pytest.approx(
        (sum(e * e for e in log["err_z_um"]) / len(log["err_z_um"])) ** 0.5, rel=1e-6
    )

    # 6. enable the output
    text = files["compensate.yaml"]
    assert "port: 9105" in text
    (tmp_path / "compensate.yaml").write_text(text.replace("port: 9105", "port: 0"))  # any free port
    assert cli("compd check-config compensate.yaml", capsys)[:2] == (0, "ok\n")
    argv = [sys.executable, "-m", "compd", *in_guide("compd run compensate.yaml").split()[1:]]
    proc = subprocess.Popen(
        argv, cwd=tmp_path, env={**os.environ, "PYTHONPATH": str(ROOT)},
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
    )
    try:
        # 7. watch, while it runs
        wait_for_status(tmp_path / "compensate.status.json", proc.pid, proc)
        rc, out, _ = cli("compd status --config compensate.yaml", capsys)
        assert rc == 0 and out.startswith("compd running") and "OBSERVE" not in out
        assert re.search(r"^z .* (starting|normal) +hold", out, re.M)
        assert re.search(r"^T_xi +[\d.]+ good", out, re.M)
        rc, out, _ = cli("compd status --config compensate.yaml --json", capsys)
        status = json.loads(out)
        assert rc == 0 and status["alive"] is True and status["observe"] is False
        assert status["sink"]["kind"] == "pci1756" and "would_write" not in status["sink"]
        with urllib.request.urlopen(status["metrics_url"], timeout=10) as resp:
            metrics = resp.read().decode()
        assert 'compd_correction_micrometres{axis="z"}' in metrics
        assert "compd_observe_mode 0.0" in metrics
        out, err = proc.communicate(timeout=120)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.communicate()
    assert proc.returncode == 0, err
    before, after = map(float, re.search(r"without compensation ([\d.]+) um, with ([\d.]+) um", out).groups())
    assert after < 0.2 * before, out
    comp = read_csv(tmp_path / "compensated.csv")
    assert min(comp["applied_z_um"]) < -10.0  # corrections reached the (emulated) card
    rc, _, err = cli("compd status --config compensate.yaml", capsys)
    assert rc == 1 and "stopped" in err

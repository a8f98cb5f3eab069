"""compd stands alone: it never names the simulator, and a wheel of the compd package only
installs and runs (check-config, run against a Modbus device, fit, predict, replay) where
neither hil_sim nor the rig can be imported."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import sysconfig
import time
import tomllib
import zipfile
from pathlib import Path

import numpy as np
import pytest
import yaml

ROOT = Path(__file__).resolve().parents[2]
NOT_OURS = ("compd", "hil_sim", "rig", "__editable__")

# 4 K above T0: error α L ΔT = 13.6e-6 × 165 mm × 4 K = 8.98 µm; correction −8.98 µm
WANT_UM = -13.6e-6 * 165.0 * 1000.0 * 4.0


def test_compd_never_names_the_simulator():
    """Not in code, comments, docstrings or strings: compd knows no simulator package."""
    found = []
    for path in sorted((ROOT / "compd").rglob("*")):
        if not path.is_file() or "__pycache__" in path.parts:
            continue
        for n, line in enumerate(path.read_text(encoding="utf-8", errors="replace").splitlines(), 1):
            if "hil_sim" in line:
                found.append(f"{path.relative_to(ROOT)}:{n}: {line.strip()}")
    assert found == []


def _toml(value: object) -> str:
    return json.dumps(value, ensure_ascii=False)  # strings and lists of strings: the same in TOML


def _compd_only_project(src: Path) -> None:
    """compd/ and a pyproject that packages it alone: the repository's build system, name,
    version, dependencies and `compd` script, no other package, no entry point of the rig."""
    import shutil

    shutil.copytree(ROOT / "compd", src / "compd", ignore=shutil.ignore_patterns("__pycache__"))
    ours = tomllib.loads((ROOT / "pyproject.toml").read_text(encoding="utf-8"))
    build, project = ours["build-system"], ours["project"]
    lines = [
        "[build-system]",
        f"requires = {_toml(build['requires'])}",
        f"build-backend = {_toml(build['build-backend'])}",
        "",
        "[project]",
        *(f"{key} = {_toml(project[key])}" for key in ("name", "version", "requires-python", "dependencies")),
        "",
        "[project.scripts]",
        *(f"{name} = {_toml(target)}" for name, target in project["scripts"].items()),
        "",
        "[tool.setuptools.packages.find]",
        'include = ["compd*"]',
    ]
    (src / "pyproject.toml").write_text("\n".join(lines) + "\n", encoding="utf-8")


def _site_without_the_project(links: Path) -> Path:
    """The running environment's packages (numpy, pymodbus, …) as symlinks, minus compd,
    hil_sim, the rig and the editable-install hooks that would find them."""
    site = Path(sysconfig.get_paths()["purelib"])
    links.mkdir()
    for entry in site.iterdir():
        if entry.name.startswith(NOT_OURS) or entry.suffix == ".pth":
            continue
        (links / entry.name).symlink_to(entry)
    return links


@pytest.fixture(scope="module")
def compd_alone(tmp_path_factory: pytest.TempPathFactory) -> dict[str, object]:
    """A wheel of compd alone, installed into a folder; how to run Python on it."""
    tmp = tmp_path_factory.mktemp("alone")
    src, dist, target = tmp / "src", tmp / "dist", tmp / "site"
    src.mkdir()
    _compd_only_project(src)
    quiet = {"capture_output": True, "text": True, "timeout": 300}
    r = subprocess.run([sys.executable, "-m", "pip", "wheel", "-q", "--no-deps", "-w", str(dist), str(src)], **quiet)
    assert r.returncode == 0, r.stderr
    wheel = next(dist.glob("compd-*.whl"))
    r = subprocess.run(
        [sys.executable, "-m", "pip", "install", "-q", "--no-deps", "--target", str(target), str(wheel)], **quiet
    )
    assert r.returncode == 0, r.stderr
    links = _site_without_the_project(tmp / "deps")
    # -S: no site module, so no .pth file and no editable-install finder is loaded; the
    # packages come from PYTHONPATH only, and the working folder is not the repository
    env = {k: v for k, v in os.environ.items() if not k.startswith(("PYTHON", "COMPD"))}
    env["PYTHONPATH"] = os.pathsep.join([str(target), str(links)])
    work = tmp / "work"
    work.mkdir()
    return {"wheel": wheel, "python": [sys.executable, "-S"], "env": env, "cwd": work}


def _run(alone: dict[str, object], *args: str, timeout_s: float = 120.0) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [*alone["python"], *args],
        capture_output=True,
        text=True,
        timeout=timeout_s,  # type: ignore[misc]
        env=alone["env"],
        cwd=alone["cwd"],  # type: ignore[arg-type]
    )


def test_the_wheel_holds_compd_only(compd_alone):
    with zipfile.ZipFile(compd_alone["wheel"]) as z:
        top = {name.split("/", 1)[0] for name in z.namelist()}
        entry_points = next(n for n in z.namelist() if n.endswith(".dist-info/entry_points.txt"))
        text = z.read(entry_points).decode()
    assert top == {"compd", "compd-0.1.0.dist-info"}
    assert "compd = compd.cli:main" in text and "compd.sources" not in text and "compd.commands" not in text


def test_neither_the_simulator_nor_the_rig_can_be_imported(compd_alone):
    r = _run(compd_alone, "-c", "import compd, pymodbus, numpy; print(compd.__file__)")
    assert r.returncode == 0, r.stderr
    assert Path(r.stdout.strip()).is_relative_to(Path(str(compd_alone["env"]["PYTHONPATH"]).split(os.pathsep)[0]))
    for name in ("hil_sim", "rig"):
        r = _run(compd_alone, "-c", f"import {name}")
        assert r.returncode == 1 and "ModuleNotFoundError" in r.stderr, (name, r.stderr)


def _log(path: Path) -> None:
    """A spindle warming up: T_xi rises 6 K, the axial error follows α L ΔT."""
    t = np.arange(0.0, 4 * 3600.0 + 1, 60.0)
    temp = 20.0 + 6.0 * (1 - np.exp(-t / 3600.0))
    err = 13.6e-6 * 165.0 * 1000.0 * (temp - 20.0)
    rows = "\n".join(f"{a:g},{b:.4f},{c:.4f}" for a, b, c in zip(t, temp, err, strict=True))
    path.write_text("t_s,T_xi,err_z_um\n" + rows + "\n")


def test_fit_predict_and_replay_into_the_software_plc(compd_alone):
    work: Path = compd_alone["cwd"]  # type: ignore[assignment]
    _log(work / "day.csv")
    r = _run(compd_alone, "-m", "compd", "fit", "--kind", "mlr", "--log", "day.csv", "--out", "m.yaml")
    assert r.returncode == 0, r.stderr
    r = _run(compd_alone, "-m", "compd", "predict", "m.yaml", "--log", "day.csv", "--out", "pred.csv")
    assert r.returncode == 0, r.stderr
    assert (work / "pred.csv").read_text().splitlines()[0] == "t_s,pred_z_um"
    r = _run(compd_alone, "-m", "compd", "replay", "--model", "m.yaml", "--log", "day.csv", "--report", "rep.json")
    assert r.returncode == 0, r.stderr
    rep = json.loads((work / "rep.json").read_text())
    assert rep["plc"] == "in_process" and rep["codes_sent"] > 5
    assert rep["axes"]["z"]["reduction_pct"] > 80.0


def test_without_the_simulator_sim_and_bench_are_missing_one_line_exit_2(compd_alone):
    work: Path = compd_alone["cwd"]  # type: ignore[assignment]
    cfg = work / "sim.yaml"
    cfg.write_text(
        "sources:\n  - kind: sim\n    name: s\n    plant: spindle\n    scenario: x.yaml\n"
        "model: {kind: xi_spindle, inputs: [T_xi], outputs: [z], params: {alpha_per_k: 1.0e-5, length_mm: 100}}\n"
        "sink: {kind: pci1756}\n"
    )
    r = _run(compd_alone, "-m", "compd", "check-config", str(cfg))
    assert r.returncode == 2 and len(r.stderr.splitlines()) == 1, r.stderr
    assert "sim.yaml:2" in r.stderr and "unknown source kind 'sim'" in r.stderr, r.stderr
    r = _run(compd_alone, "-m", "compd", "bench", "--cycles", "10")
    assert r.returncode == 2 and len(r.stderr.splitlines()) == 1, r.stderr
    assert "compd bench" in r.stderr and "not installed" in r.stderr, r.stderr


def test_check_config_and_run_against_a_modbus_pmc(compd_alone):
    """The wheel's compd reads a PT100 module and drives a PMC, both served here over Modbus TCP."""
    from compd.plc.fanuc_pmc import FanucPmc
    from hil_sim.devices.modbus_server import ModbusServerThread
    from hil_sim.devices.pt100 import Pt100Transmitter
    from hil_sim.devices.pt100_modbus import Pt100ModbusDevice
    from hil_sim.devices.scan import PmcScanThread

    work: Path = compd_alone["cwd"]  # type: ignore[assignment]
    tx = Pt100Transmitter(["T_xi"], [24.0])
    pmc = FanucPmc(step_limit_um=10)
    scan = PmcScanThread(pmc).start()
    try:
        with ModbusServerThread(Pt100ModbusDevice(tx), port=0) as pt, ModbusServerThread(pmc, port=0) as plc:
            cfg = work / "modbus.yaml"
            cfg.write_text(
                yaml.safe_dump(
                    {
                        "loop": {"period_s": 0.01},
                        "sources": [
                            {
                                "kind": "modbus",
                                "name": "pt",
                                "host": "127.0.0.1",
                                "port": pt.port,
                                "poll_period_s": 0.02,
                                "channels": [{"name": "T_xi", "address": 0}],
                            }
                        ],
                        "model": {
                            "kind": "xi_spindle",
                            "inputs": ["T_xi"],
                            "outputs": ["z"],
                            "params": {"alpha_per_k": 13.6e-6, "length_mm": 165.0, "t0_c": 20.0},
                        },
                        "guard": {"max_slew_um_per_s": 100.0},
                        "sink": {"kind": "fanuc_pmc", "host": "127.0.0.1", "port": plc.port, "max_step_um": 5},
                        "console": {"period_s": 0, "summary": False},
                    }
                )
            )
            r = _run(compd_alone, "-m", "compd", "check-config", str(cfg))
            assert r.returncode == 0 and r.stdout.strip() == "ok", r.stderr
            proc = subprocess.Popen(
                [*compd_alone["python"], "-m", "compd", "run", str(cfg), "--duration", "4", "--json", "sum.json"],
                stdout=subprocess.PIPE,
                stderr=subprocess.PIPE,
                text=True,
                env=compd_alone["env"],
                cwd=work,  # type: ignore[arg-type]
            )
            applied = []
            deadline = time.monotonic() + 120
            while proc.poll() is None and time.monotonic() < deadline:
                applied.append(pmc.applied_um()[0])
                time.sleep(0.01)
            out, err = proc.communicate(timeout=60)
            assert proc.returncode == 0, err
    finally:
        scan.stop()
    summary = json.loads((work / "sum.json").read_text())
    assert summary["loop"]["cycles"] > 10 and summary["sink"]["updates"] >= 2
    # the PMC applied the correction (within the dead-band and half an LSB) while compd ran …
    assert min(applied, key=lambda a: abs(a - WANT_UM)) == pytest.approx(WANT_UM, abs=1.5), applied[-20:]
    # … and compd walked the shift back to zero in allowed steps when it stopped
    assert pmc.applied_um() == [0.0, 0.0] and pmc.alarms() == 0

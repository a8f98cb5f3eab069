"""The daemon package alone: `compd run` and the daemon's commands never import what compd-commissioning
ships (scipy, matplotlib, the simulator, the rig, compd.identify, compd.commissioning, the OPC UA stack),
not even lazily, and each commissioning command says in one line that its package is missing, exit 2.

The commissioning package is "removed" by a `sitecustomize` on PYTHONPATH, which every Python process
of the run loads (the daemon, its forked workers and service, an agent started anew): its finder
refuses those modules as if their files were absent and notes each attempt in a file, so an import
that code caught and went on without still fails the test.
"""

from __future__ import annotations

import importlib.util
import json
import os
import signal
import subprocess
import sys
import sysconfig
import time
import types
import urllib.request
from pathlib import Path

import pytest

from tests.service_helpers import wait_running

ROOT = Path(__file__).resolve().parents[2]
WAIT_S = 120.0


def split_table() -> types.ModuleType:
    """packaging/deb/split.py, the one table of what goes into which package."""
    spec = importlib.util.spec_from_file_location("split", ROOT / "packaging" / "deb" / "split.py")
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def absent_modules() -> tuple[str, ...]:
    """What compd-commissioning ships, as modules: its folders, and the top-level modules of its
    distributions as split.py picks them from this environment (the package's build does the same)."""
    split = split_table()
    dists = split.distributions(Path(sysconfig.get_paths()["purelib"]))
    names = set().union(*(split.import_names(dists[d]) for d in split.commissioning_distributions(dists)))
    return tuple(sorted({f.replace("/", ".") for f in split.COMMISSIONING_FOLDERS} | names))


ABSENT = absent_modules()

SITECUSTOMIZE = """
import os, sys
ABSENT = {absent!r}
NOTES = {notes!r}

class Absent:
    '''The commissioning package's modules, as if their files were not installed.'''
    def find_spec(self, name, path=None, target=None):
        if any(name == a or name.startswith(a + ".") for a in ABSENT):
            with open(NOTES, "a", encoding="utf-8") as fh:
                fh.write(f"{{os.getpid()}} {{name}} {{' '.join(sys.argv)}}\\n")
            raise ModuleNotFoundError(f"No module named {{name!r}}", name=name)
        return None

sys.meta_path.insert(0, Absent())
"""

# a spindle warming over 6 h, one row a minute: what the replay source feeds the loop
CONFIG = """
loop: {{clock: sim, period_s: 1.0, speedup: 30}}
sources: [{{kind: replay, name: log, path: day.csv}}]
model: {{kind: xi_spindle, inputs: [T_xi], outputs: [z], params: {{alpha_per_k: 13.6e-6, length_mm: 165.0}}}}
guard: {{max_slew_um_per_s: {slew}, stale_after_s: 120.0}}
sink: {{kind: pci1756}}
adapt: {{}}
status: {{path: status.json}}
log: {{path: log.csv, period_s: 10}}
state: {{path: state.json}}
metrics: {{enabled: true, bind: 127.0.0.1, port: 0}}
"""


@pytest.fixture
def alone(tmp_path: Path) -> dict[str, object]:
    """The environment of the daemon package alone, its notes file and a working folder."""
    hook = tmp_path / "hook"
    hook.mkdir()
    notes = tmp_path / "imports.txt"
    notes.write_text("", encoding="utf-8")
    (hook / "sitecustomize.py").write_text(SITECUSTOMIZE.format(absent=ABSENT, notes=str(notes)), encoding="utf-8")
    env = {k: v for k, v in os.environ.items() if not k.startswith("COMPD")}
    env["PYTHONPATH"] = os.pathsep.join([str(hook), str(ROOT)])
    work = tmp_path / "work"
    work.mkdir()
    rows = ["t_s,T_xi,err_z_um"]
    for i in range(361):
        temp = 20.0 + 6.0 * (1.0 - 2.718281828 ** (-i / 60.0))
        rows.append(f"{i * 60},{temp:.4f},{13.6e-6 * 165.0 * 1000.0 * (temp - 20.0):.4f}")
    (work / "day.csv").write_text("\n".join(rows) + "\n", encoding="utf-8")
    (work / "run.yaml").write_text(CONFIG.format(slew=2.0), encoding="utf-8")
    return {"env": env, "notes": notes, "cwd": work}


def compd(alone: dict[str, object], *args: str, timeout_s: float = 60.0) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, "-m", "compd", *args],
        capture_output=True,
        text=True,
        timeout=timeout_s,
        env=alone["env"],
        cwd=alone["cwd"],
    )  # type: ignore[arg-type]


def notes(alone: dict[str, object]) -> list[str]:
    return Path(str(alone["notes"])).read_text(encoding="utf-8").splitlines()


def until(cond, what: str, timeout_s: float = WAIT_S):  # noqa: ANN001, ANN201
    end = time.monotonic() + timeout_s
    while time.monotonic() < end:
        got = cond()
        if got:
            return got
        time.sleep(0.05)
    raise AssertionError(f"no {what} in {timeout_s:g} s")


def test_the_hook_takes_the_commissioning_modules_away(alone: dict[str, object]) -> None:
    for name in ("scipy", "matplotlib", "hil_sim", "rig", "compd.identify", "compd.commissioning", "asyncua"):
        assert name in ABSENT, ABSENT
    assert not {"numpy", "yaml", "pydantic", "pymodbus", "serial", "can", "prometheus_client", "paho"} & set(ABSENT)
    r = subprocess.run(
        [sys.executable, "-c", "import numpy, yaml, pydantic, pymodbus, compd.cli\nimport scipy"],
        capture_output=True,
        text=True,
        timeout=60,
        env=alone["env"],
        cwd=alone["cwd"],
    )
    assert r.returncode == 1 and "No module named 'scipy'" in r.stderr, r.stderr
    assert [n.split()[1] for n in notes(alone)] == ["scipy"]


def test_the_daemon_runs_reloads_and_answers_without_them(alone: dict[str, object]) -> None:
    """check-config, run (workers, service, metrics, probe socket, log, state), status, probe, a
    reload and SIGTERM, all with the commissioning package absent: none of it so much as tries it."""
    work = Path(str(alone["cwd"]))
    r = compd(alone, "check-config", "run.yaml")
    assert (r.returncode, r.stdout.strip()) == (0, "ok"), r.stderr
    err = work / "run.err"
    with open(err, "w", encoding="utf-8") as fh:
        proc = subprocess.Popen(
            [sys.executable, "-m", "compd", "run", "run.yaml"],
            cwd=work,
            env=alone["env"],
            stdout=subprocess.PIPE,
            stderr=fh,
            text=True,
        )  # type: ignore[arg-type]
    try:
        status = wait_running(work / "status.json", proc, WAIT_S, after_cycles=5)
        with urllib.request.urlopen(status["metrics_url"], timeout=30) as page:
            assert b"compd_" in page.read()
        until(
            lambda: json.loads((work / "status.json").read_text())["axes"]["z"].get("prediction_um") is not None,
            "prediction",
        )
        r = compd(alone, "status", "--status", "status.json")
        assert r.returncode == 0 and "z" in r.stdout, r.stdout + r.stderr
        r = compd(alone, "probe", "--config", "run.yaml", "--axis", "z", "--error-um", "0.5")
        assert r.returncode == 0 and "probe z error 0.5 um" in r.stdout, r.stdout + r.stderr
        (work / "run.yaml").write_text(CONFIG.format(slew=3.0), encoding="utf-8")
        proc.send_signal(signal.SIGHUP)
        until(lambda: "event=reloaded" in err.read_text(encoding="utf-8") or proc.poll() is not None, "reload")
        assert proc.poll() is None, err.read_text(encoding="utf-8")
        wait_running(work / "status.json", proc, WAIT_S)
    finally:
        if proc.poll() is None:
            proc.send_signal(signal.SIGTERM)
        out, _ = proc.communicate(timeout=60)
    text = err.read_text(encoding="utf-8")
    assert proc.returncode == 0, text
    assert "cycles" in out and "internal error" not in text and "Traceback" not in text, out + text
    assert (work / "state.json").is_file() and len((work / "log.csv").read_text().splitlines()) > 1
    assert notes(alone) == [], "the daemon tried to import what compd-commissioning ships"


COMMANDS = [
    ("fit", "--kind", "mlr", "--log", "day.csv", "--out", "m.yaml"),
    ("fit", "--kind", "all", "--log", "day.csv", "--out", "models"),
    ("predict", "m.yaml", "--log", "day.csv", "--out", "p.csv"),
    ("score", "m.yaml", "--log", "day.csv"),
    ("xi", "--profile", "profile.csv"),
    ("replay", "--model", "m.yaml", "--log", "day.csv", "--report", "r.json"),
    ("replay", "run.yaml", "--log", "day.csv"),
    ("plot", "log.csv", "--out", "trend.png"),
    ("report", "--fit", "fit.json", "--replay", "r.json", "--out", "report.html"),
    ("testplan", "--max-rpm", "12000", "--hours", "24", "--out", "plan.csv"),
    ("output-test", "run.yaml", "--axis", "z", "--um", "1", "--yes"),
    ("promote", "run.yaml"),
    ("docs", "--out", "configuration.md"),
]


@pytest.mark.parametrize("args", COMMANDS, ids=lambda a: " ".join(a[:3]))
def test_a_commissioning_command_names_the_missing_package(alone: dict[str, object], args: tuple[str, ...]) -> None:
    r = compd(alone, *args)
    assert r.returncode == 2, r.stdout + r.stderr
    assert r.stderr == f"compd {args[0]}: part of the compd-commissioning package, which is not installed\n"
    assert r.stdout == ""
    assert notes(alone), "the command did try its package"
    assert sorted(p.name for p in Path(str(alone["cwd"])).iterdir()) == ["day.csv", "run.yaml"], "wrote nothing"


def test_the_kinds_and_extras_of_the_commissioning_package_name_it(alone: dict[str, object]) -> None:
    """The simulator's source (the shipped config's), the rig's bench, the OPC UA server and
    `compd fit --help`: one line naming compd-commissioning, exit 2 (the help: a line in it, exit 0)."""
    r = compd(alone, "check-config", str(ROOT / "configs" / "service.yaml"))
    assert r.returncode == 2 and r.stderr.count("\n") == 1, r.stderr
    assert r.stderr.endswith(
        "sources[0].kind: source kind 'sim' is part of the compd-commissioning package, which is not installed\n"
    ), r.stderr
    r = compd(alone, "bench")
    assert (r.returncode, r.stderr) == (
        2,
        "compd: `compd bench` is part of the compd-commissioning package, which is not installed\n",
    )
    work = Path(str(alone["cwd"]))
    (work / "opcua.yaml").write_text(
        CONFIG.format(slew=2.0).replace("metrics:", "opcua: {certificate: s.pem, private_key: s.key}\nmetrics:"),
        encoding="utf-8",
    )
    r = compd(alone, "check-config", "opcua.yaml")
    assert r.returncode == 2 and r.stderr.count("\n") == 1, r.stderr
    assert r.stderr.endswith(
        "opcua: needs the Python module asyncua, which is not installed: install the compd-commissioning package\n"
    ), r.stderr
    r = compd(alone, "opcua-cert", "--cert", "c/s.pem", "--key", "c/s.key")
    assert (r.returncode, r.stderr) == (2, "compd: needs the plant extra: install the compd-commissioning package\n")
    r = compd(alone, "fit", "--help")
    assert r.returncode == 0 and "compd fit is part of the compd-commissioning package" in r.stdout, r.stderr

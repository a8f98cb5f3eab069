"""/metrics as Prometheus's own checker sees it: `promtool check metrics` on every family and on a live scrape.

Every family compd defines, and a daemon's live scrape; promtool is Debian's prometheus package, unpacked by the
Makefile.
"""

from __future__ import annotations

import os
import re
import shutil
import subprocess
import urllib.request
from pathlib import Path

import pytest

from compd.config import load_config
from compd.daemon.app import App
from compd.service.metrics import MetricsServer, families
from compd.service.status import snapshot
from tests.conftest import ROOT
from tests.service_helpers import sim_config

pytest.importorskip("prometheus_client")  # the `metrics` extra; the `test` extra installs it


def _promtool() -> str:
    here = ROOT / "build" / "tools" / "promtool"
    found = str(here) if here.exists() else shutil.which("promtool")
    assert found, "no promtool: `make build/tools/promtool` unpacks it from Debian's prometheus package"
    return found


def _check(text: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run([_promtool(), "check", "metrics"], input=text, capture_output=True, text=True, timeout=60)


def test_promtool_finds_nothing_in_any_family_compd_defines() -> None:
    from prometheus_client import CollectorRegistry, generate_latest

    class Catalogue:
        def collect(self):  # noqa: ANN202
            return families()

    reg = CollectorRegistry()
    reg.register(Catalogue())
    text = generate_latest(reg).decode()
    r = _check(text)
    assert r.returncode == 0 and r.stdout == "" and r.stderr == "", r.stdout + r.stderr
    assert "micrometres" not in text  # base units only (docs/metrics.md lists the old names)


def test_a_live_scrape_passes_promtool_and_says_which_compd_and_which_processes(tmp_path: Path) -> None:
    app = App(load_config(sim_config(tmp_path, duration_s=600)))
    app.run()
    snap = snapshot(app.loop, state="running", observe=False)
    snap["service_pid"] = os.getpid()
    snap["processes"] = [{"name": "poll-pt", "pid": os.getppid(), "up": True, "restarts": 0, "lost": None}]
    server = MetricsServer("127.0.0.1", 0)
    url = server.start()
    try:
        server.update(snap, app.loop.stats)
        with urllib.request.urlopen(url, timeout=10) as resp:
            text = resp.read().decode()
    finally:
        server.stop()
    r = _check(text)
    assert r.returncode == 0 and r.stdout == "" and r.stderr == "", r.stdout + r.stderr
    from compd import version

    assert re.search(rf'^compd_build_info{{python="[\d.]+",version="{re.escape(version())}"}} 1\.0$', text, re.M)
    assert re.search(r"^process_cpu_seconds_total \d", text, re.M)  # the serving process's own
    for proc in ("cycle", "service", "poll-pt"):
        assert re.search(rf'^compd_process_cpu_seconds_total{{process="{proc}"}} [\d.e+-]+$', text, re.M), proc
        assert re.search(rf'^compd_process_resident_memory_bytes{{process="{proc}"}} [1-9]', text, re.M), proc
    z = snap["axes"]["z"]["correction_um"]
    got = float(re.search(r'^compd_correction_meters{axis="z"} (\S+)$', text, re.M).group(1))
    assert got == pytest.approx(z * 1e-6)
    assert re.search(r'^compd_signal_celsius{signal="T_xi"} 2\d\.', text, re.M)  # a PT100 in °C

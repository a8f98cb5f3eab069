"""The figures the README quotes from commands are what those commands give (same seed)."""

from __future__ import annotations

import re
import subprocess
import sys
from pathlib import Path

import pytest

from compd.commissioning import fitting

ROOT = Path(__file__).resolve().parent.parent


@pytest.mark.slow
def test_lvr_library_span_figures(tmp_path: Path) -> None:
    text = " ".join((ROOT / "README.md").read_text(encoding="utf-8").split())
    m = re.search(
        r"\(`python -m hil_sim log --scenario (\S+) --rate-s (\d+)`\), a span of (\d+) fitted one component"
        r" with ([\d.]+) µm RMSE on (\w+) where the log itself gives ([\d.]+) µm, a span of (\d+) gave ([\d.]+) µm",
        text,
    )
    assert m, "the README's library_span sentence changed: update this test"
    scenario, rate, span_a, rmse_a, axis, rmse_log, span_b, rmse_b = m.groups()
    r = subprocess.run(
        [
            sys.executable,
            "-m",
            "hil_sim",
            "log",
            "--scenario",
            str(ROOT / scenario),
            "--rate-s",
            rate,
            "--out",
            str(tmp_path / "gantry.csv"),
        ],
        capture_output=True,
        text=True,
        timeout=300,
        cwd=tmp_path,
    )
    assert r.returncode == 0, r.stderr
    log = fitting.read_fit_log(tmp_path / "gantry.csv")

    def rmse(options: dict) -> tuple[float, int]:
        oc = fitting.fit_model("lvr", log, None, None, options, baseline=False)
        return oc.report["axes"][axis]["rmse_um"], oc.model.params.n_components

    for options, quoted in (
        ({}, rmse_log),
        ({"library_span": int(span_a)}, rmse_a),
        ({"library_span": int(span_b)}, rmse_b),
    ):
        got, n = rmse(options)
        digits = len(quoted.partition(".")[2])
        assert abs(got - float(quoted)) <= 0.51 * 10.0**-digits, (options, got, quoted)
        if options.get("library_span") == int(span_a):
            assert n == 1  # "fitted one component"

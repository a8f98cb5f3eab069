"""The most a probe-updated estimate held between probes can give on a simulated axis (issue 17).

At every probe time the script fits offset b, gain g and slope m exactly (least squares)
to the plant's whole true error profile E(y) minus the model's prediction p(y) there,
holds them until the next probe, and scores the day along the axis's own path:

    ê(t) = p(t) + b_k + g_k p(t) + m_k y(t)   for t_k ≤ t < t_k + every

No single probe knows the whole profile, so no estimator of that form does better;
what is left is the part of the model's error that changes between probes. The day
comes from `python -m hil_sim log` (with `--profile`), the prediction from
`compd predict`, both run here.

    python scripts/probe_bound.py --model build/accept/feed_axis_feed_axis_analytic.yaml
"""

from __future__ import annotations

import argparse
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from compd.log import read_log  # noqa: E402

FORMS = {"b": (0,), "b,g": (0, 1), "b,m": (0, 2), "b,g,m": (0, 1, 2)}


def _features(p: np.ndarray, y_m: np.ndarray, cols: tuple[int, ...]) -> np.ndarray:
    f = np.column_stack([np.ones_like(p), p, y_m])
    return f[:, list(cols)]


def bound_pct(
    day: Path, pred: Path, prof: Path, prof_pred: Path, axis: str, every_s: float, cols: tuple[int, ...]
) -> float:
    """RMS reduction % of the held estimate refitted to the whole profile every `every_s`."""
    d, p = read_log(day), read_log(pred)
    t, e, pr, y = d.t_s, d.col(f"err_{axis}_um"), p.col(f"pred_{axis}_um"), d.col(f"pos_{axis}_mm") / 1000.0
    g, gp = read_log(prof), read_log(prof_pred)
    gt, ge, gpr, gy = g.t_s, g.col(f"err_{axis}_um"), gp.col(f"pred_{axis}_um"), g.col(f"pos_{axis}_mm") / 1000.0
    est = pr.copy()
    k = 1
    while k * every_s <= t[-1]:
        tk = k * every_s
        at = np.isclose(gt, tk)
        if not at.any():
            raise SystemExit(f"no profile at t = {tk:.0f} s: --profile-every-s must divide the probe interval")
        c = np.linalg.lstsq(_features(gpr[at], gy[at], cols), ge[at] - gpr[at], rcond=None)[0]
        held = (t >= tk) & (t < tk + every_s)
        est[held] = pr[held] + _features(pr[held], y[held], cols) @ c
        k += 1
    rms = lambda x: float(np.sqrt(np.mean(x * x)))  # noqa: E731
    return 100.0 * (1.0 - rms(e - est) / rms(e))


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--model", required=True, help="model YAML (a feed_axis or other position-dependent model)")
    ap.add_argument("--scenario", default=str(ROOT / "hil_sim/scenarios/feed_axis_unseen.yaml"))
    ap.add_argument("--axis", default="y")
    ap.add_argument("--every-s", type=float, nargs="+", default=[3600.0, 1800.0, 600.0])
    a = ap.parse_args()
    py = sys.executable
    with tempfile.TemporaryDirectory() as tmp:
        w = Path(tmp)
        step = min(600.0, *a.every_s)
        subprocess.run(
            [
                py,
                "-m",
                "hil_sim",
                "log",
                "--scenario",
                a.scenario,
                "--out",
                str(w / "day.csv"),
                "--rate-s",
                "10",
                "--profile",
                str(w / "prof.csv"),
                "--profile-every-s",
                str(step),
            ],
            check=True,
            cwd=ROOT,
            stdout=subprocess.DEVNULL,
        )
        for log, out in (("day.csv", "pred.csv"), ("prof.csv", "prof_pred.csv")):
            subprocess.run(
                [py, "-m", "compd", "predict", "--log", str(w / log), "--out", str(w / out), a.model],
                check=True,
                cwd=ROOT,
                stdout=subprocess.DEVNULL,
            )
        d, p = read_log(w / "day.csv"), read_log(w / "pred.csv")
        e = d.col(f"err_{a.axis}_um")
        alone = 100.0 * (1.0 - np.sqrt(np.mean((e - p.col(f"pred_{a.axis}_um")) ** 2)) / np.sqrt(np.mean(e * e)))
        print(f"model alone: {alone:.1f} % RMS reduction")
        print("held estimate refitted to the true profile at every probe (RMS reduction %):")
        print("  every_s " + "".join(f"{f:>8}" for f in FORMS))
        for every in a.every_s:
            row = [
                bound_pct(w / "day.csv", w / "pred.csv", w / "prof.csv", w / "prof_pred.csv", a.axis, every, c)
                for c in FORMS.values()
            ]
            print(f"  {every:7.0f} " + "".join(f"{v:8.1f}" for v in row))
    return 0


if __name__ == "__main__":
    sys.exit(main())

"""How well lvr compensates the gantry with each sensor missing: the table in docs/reliability.md.

Simulates the gantry's training and unseen days (`python -m hil_sim log`), fits lvr on the
training day (`compd fit --kind lvr`), then replays the unseen day with every sensor removed
in turn through `evaluate_degraded` (the missing rise replaced by its conditional expectation
given the others, from the fit data's covariance). RMS residual = RMS(err + correction) over
the day, correction = −prediction. An axis whose added σ exceeds `degraded_max_sigma_um`
refuses (NaN → the guard's fault policy); the table shows what it would have done anyway.

    .venv/bin/python scripts/degraded_table.py --doc docs/reliability.md
"""

from __future__ import annotations

import argparse
import contextlib
import io
import sys
import tempfile
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from compd.cli import main as compd_main  # noqa: E402
from compd.commissioning.faultdoc import replace_block  # noqa: E402
from compd.config import resolve_model  # noqa: E402
from compd.core.config import Document  # noqa: E402
from compd.cycle.pipeline import build_model  # noqa: E402
from compd.log import read_log  # noqa: E402
from hil_sim.__main__ import main as hil_main  # noqa: E402
from hil_sim.scenario import SCENARIOS  # noqa: E402


def _quiet(fn, argv: list[str]) -> None:  # noqa: ANN001
    with contextlib.redirect_stdout(io.StringIO()), contextlib.redirect_stderr(io.StringIO()):
        code = fn(argv)
    if code:
        raise SystemExit(f"{argv[0]} failed with exit {code}")


def degraded_rows(rate_s: float) -> tuple[list[str], list[dict], dict]:
    """Per removed sensor: RMS residual per axis (µm), added σ per axis, served or refused."""
    with tempfile.TemporaryDirectory() as tmp:
        d = Path(tmp)
        for day in ("train", "unseen"):
            _quiet(
                hil_main,
                [
                    "log",
                    "--scenario",
                    str(SCENARIOS / f"gantry_{day}.yaml"),
                    "--out",
                    str(d / f"{day}.csv"),
                    "--rate-s",
                    str(rate_s),
                ],
            )
        _quiet(compd_main, ["fit", "--kind", "lvr", "--log", str(d / "train.csv"), "--out", str(d / "lvr.yaml")])
        doc = Document({}, str(d / "lvr.yaml"))
        spec = resolve_model({"kind": "lvr", "file": str(d / "lvr.yaml")}, doc, ("model",), d)
        model = build_model(spec)
        log = read_log(d / "unseen.csv")
    X = log.matrix(model.inputs)
    E = log.matrix([f"err_{a}_um" for a in model.outputs])
    model.start(X[0], float(log.t_s[0]))
    out = np.zeros(len(model.outputs))
    full = np.array([_eval(model, x, out) for x in X])
    base = {
        "none": np.sqrt(np.mean(E**2, axis=0)),
        "all": np.sqrt(np.mean((E - full) ** 2, axis=0)),
    }
    rows = []
    limit = model.params.degraded_max_sigma_um
    masks = [(name, [j]) for j, name in enumerate(model.inputs)]
    masks += [(f"all of {', '.join(g)}", [model.inputs.index(n) for n in g]) for g in _groups(model.inputs)]
    for name, missing in masks:
        j = missing
        good = np.ones(len(model.inputs), dtype=bool)
        good[j] = False
        B, b0, sigma = model._degraded_form(good)  # what evaluate_degraded uses, without the refusal
        pred = (X - model.x0) * good @ B + b0
        served = []
        for x in X[:3]:  # the real path: evaluate_degraded, NaN where the axis refuses
            xb = x.copy()
            xb[j] = np.nan
            model.evaluate_degraded(xb, good, 0.0, out)
            served.append(np.isfinite(out))
        rows.append(
            {
                "sensor": name,
                "rms_um": np.sqrt(np.mean((E - pred) ** 2, axis=0)),
                "sigma_um": sigma,
                "served": np.all(served, axis=0),
            }
        )
    return list(model.outputs), rows, {**base, "limit": limit}


def _groups(names: list[str]) -> list[list[str]]:
    """Sensors that share a prefix and a numbering style (T1A…T1D, T10…T14): one cable loom."""
    groups: dict[str, list[str]] = {}
    for n in names:
        if len(n) >= 3:
            groups.setdefault(n[:-1] + ("#" if n[-1].isdigit() else "@"), []).append(n)
    return [g for g in groups.values() if len(g) > 1]


def _eval(model, x: np.ndarray, out: np.ndarray) -> np.ndarray:  # noqa: ANN001
    model.evaluate(x, 0.0, out)
    return out.copy()


def render(axes: list[str], rows: list[dict], base: dict, rate_s: float) -> str:
    head = ["sensor removed"] + [f"RMS {a} µm" for a in axes] + [f"added σ {a} µm" for a in axes] + ["axes served"]
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    lines.append(
        "| (no compensation) | " + " | ".join(f"{v:.2f}" for v in base["none"]) + " | " + " | " * len(axes) + " |"
    )
    lines.append(
        "| (none: all 19 sensors) | "
        + " | ".join(f"{v:.2f}" for v in base["all"])
        + " | "
        + " | ".join("0" for _ in axes)
        + " | "
        + ", ".join(axes)
        + " |"
    )
    for r in rows:
        served = [a for a, s in zip(axes, r["served"], strict=True) if s]
        cells = [r["sensor"]] + [f"{v:.2f}" for v in r["rms_um"]] + [f"{v:.2f}" for v in r["sigma_um"]]
        cells.append(", ".join(served) if served else "none (refused)")
        lines.append("| " + " | ".join(cells) + " |")
    refused = {
        a: [r["sensor"] for r in rows if not r["served"][i] and not r["sensor"].startswith("all of")]
        for i, a in enumerate(axes)
    }
    text = [
        f"Gantry, lvr fitted on `gantry_train.yaml`, evaluated on `gantry_unseen.yaml` (24 h, one row per "
        f"{rate_s:g} s). RMS residual = RMS(error + correction) over the unseen day with that sensor removed "
        f"(its rise replaced by the conditional expectation given the others); added σ = the prediction "
        f"uncertainty the missing sensor adds, from the fit data's covariance. An axis refuses (NaN → its "
        f"fault policy) when its added σ exceeds `degraded_max_sigma_um` = {base['limit']:g} µm; the RMS shown "
        f"for a refused axis is what it would have done.",
        "",
        *lines,
        "",
    ]
    for a in axes:
        if refused[a]:
            text.append(f"* Axis {a} refuses to do without: {', '.join(refused[a])}.")
        else:
            text.append(f"* Axis {a} does without any single sensor.")
    for r in rows:
        if r["sensor"].startswith("all of"):
            lost = [a for a, ok in zip(axes, r["served"], strict=True) if not ok]
            if lost:
                text.append(f"* Without {r['sensor'][7:]} together, {', '.join(lost)} refuses.")
    return "\n".join(text)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--doc", type=Path, default=None, help="rewrite the degraded block of this page")
    ap.add_argument("--rate-s", type=float, default=60.0, help="seconds between log rows")
    args = ap.parse_args(argv)
    axes, rows, base = degraded_rows(args.rate_s)
    table = render(axes, rows, base, args.rate_s)
    print(table)
    if args.doc is not None:
        args.doc.write_text(replace_block(args.doc.read_text(encoding="utf-8"), "degraded", table), encoding="utf-8")
    return 0


if __name__ == "__main__":
    sys.exit(main())

"""Issue 29: the ξ-point spindle whose ξ sensor lags the rotor, fitted with and without compd's sensor lead.

usage: python scripts/lag_sweep.py [--lags-s 1 60 120 200 300] [--rate-s 10] [--json FILE] [--plant YAML]

For each lag τ the simulated spindle (hil_sim's paper-003 plant with a rotor that follows its
heat in minutes, FAST_ROTOR, on its training and unseen days in hil_sim/scenarios; `--plant '{}'`
for the paper's own) is logged with the ξ sensor T_xi lagging its point of the rotor by τ
(the plant's `sensor_lag_s`); `compd fit --kind xi_spindle --inputs T_xi speed_rpm --target
err_z_um` fits the training day with the lead chosen held out (`lag: auto`, the default) and
without it (`lag: off`, the paper's single gain); each model is replayed on the unseen day
into the FANUC PMC's word in process (compd.commissioning.replay, as `compd replay --model`). The table
gives the RMS reduction of the axial error and the lead the fit kept. The issue's goal: 90 %
with a lag of 200 s.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from hil_sim.logcmd import run_log  # noqa: E402
from hil_sim.plants import PLANTS  # noqa: E402
from hil_sim.scenario import SCENARIOS, Scenario  # noqa: E402

GOAL_PCT = 90.0
GOAL_LAG_S = 200.0
# a rotor that follows its heat in minutes (thin, well cooled, its bearings working hard): hil_sim's
# paper-003 spindle (radius 40 mm, h 30 W/m²K) follows in tens of minutes, so a ξ sensor that lags
# by minutes costs it little; here the lag is what the single-gain form misses
FAST_ROTOR = {"radius_mm": 22.0, "h_w_m2k": 80.0, "front_w_per_krpm": 2.5, "rear_w_per_krpm": 1.0}


def day_log(day: str, lag_s: float, rate_s: float, out: Path, plant: dict | None = None) -> Path:
    """The spindle's `day` (train or unseen) logged with T_xi lagging by `lag_s` (and `plant` params)."""
    sc = Scenario.load(SCENARIOS / f"spindle_{day}.yaml")
    params = {**sc.params, **(plant or {}), "sensor_lag_s": {"T_xi": lag_s}}
    run_log(PLANTS.get("spindle")(sc, params), out, rate_s)
    return out


def sweep(lags_s: list[float], rate_s: float, work: Path, plant: dict | None = None) -> list[dict]:
    """Per lag: the reduction with the lead (`lag: auto`) and without (`lag: off`), and the lead kept."""
    from compd.commissioning import fitting
    from compd.commissioning.replay import _pmc_sink, replay_log
    from compd.log import read_log

    rows = []
    for lag in lags_s:
        train = fitting.read_fit_log(day_log("train", lag, rate_s, work / f"train_{lag:g}.csv", plant))
        unseen = read_log(day_log("unseen", lag, rate_s, work / f"unseen_{lag:g}.csv", plant), allow_nan=True)
        row: dict = {"lag_s": lag}
        for tag, opts in (("lead", {}), ("no_lead", {"lag": "off"})):
            oc = fitting.fit_model("xi_spindle", train, ["T_xi", "speed_rpm"], ["err_z_um"], opts, baseline=False)
            rep = replay_log(unseen, fitting.clone(oc.model), _pmc_sink()).report
            row[tag] = rep["axes"]["z"]["reduction_pct"]
            if tag == "lead":
                row["lead_s"] = oc.report["details"]["lag"].get("lead_s", {}).get("T_xi", 0.0)
        rows.append(row)
    return rows


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--lags-s", type=float, nargs="+", default=[1.0, 60.0, 120.0, 200.0, 300.0])
    ap.add_argument("--rate-s", type=float, default=10.0, help="log period of both days (s)")
    ap.add_argument("--json", default=None, help="write the rows here")
    ap.add_argument(
        "--plant",
        default=None,
        metavar="YAML",
        help="spindle plant params over the scenario's (default: FAST_ROTOR; '{}' for the paper's spindle)",
    )
    args = ap.parse_args(argv)
    import yaml

    plant = yaml.safe_load(args.plant) if args.plant is not None else FAST_ROTOR
    os.environ.setdefault("TQDM_DISABLE", "1")
    with tempfile.TemporaryDirectory() as d:
        rows = sweep(args.lags_s, args.rate_s, Path(d), plant)
    print("| T_xi lag | with compd's lead | lead kept | paper's single gain (lag off) |")
    print("|---|---|---|---|")
    for r in rows:
        print(f"| {r['lag_s']:g} s | {r['lead']:.1f} % | {r['lead_s']:g} s | {r['no_lead']:.1f} % |")
    if args.json:
        Path(args.json).write_text(json.dumps(rows, indent=1))
    at_goal = [r for r in rows if r["lag_s"] == GOAL_LAG_S]
    return 1 if at_goal and at_goal[0]["lead"] < GOAL_PCT else 0


if __name__ == "__main__":
    sys.exit(main())

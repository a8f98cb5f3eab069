"""AR(1) on the hil_sim lathe: the ambient-aware form (C3, `--ambient`) against the paper's form
on the unseen day (other speeds, a shop that warms by ~3 °C)."""

from __future__ import annotations

from pathlib import Path

import yaml

from compd.commissioning import fitting
from hil_sim.logcmd import run_log
from hil_sim.plants import PLANTS
from hil_sim.scenario import Scenario

SCEN = Path(__file__).resolve().parents[2] / "hil_sim" / "scenarios"


def _log(data: dict, out: Path) -> fitting.Log:
    sc = Scenario.from_dict(data)
    run_log(PLANTS.get("lathe")(sc, sc.params), out, 60.0)
    return fitting.read_fit_log(out)


def _unseen_rmse(train: fitting.Log, unseen: fitting.Log, ambient: str | None) -> float:
    # the paper's single C1 and its linear C2 between speeds (this lathe's effective exponent is
    # near 1), with and without C3
    opts: dict = {"c1_by_speed": False, "ambient": ambient or "none", "c2_exponent": "linear"}
    oc = fitting.fit_model("ar1", train, ["T3"], None, opts, baseline=False)
    pred = fitting.predict_log(oc.model, unseen)
    return fitting.scores(oc.model, unseen, ["err_z_um"], pred)["z"]["rmse_um"]


def test_ambient_aware_ar1_beats_the_paper_form_on_the_unseen_day(tmp_path):
    train = yaml.safe_load((SCEN / "lathe_train.yaml").read_text())
    # the training day's duty cycle in a shop whose ambient drifts and swings (C3 needs
    # ambient variation to be identified; the quiet-shop day's ±0.5 °C does not separate
    # it from the bed term: there the ambient-aware fit does worse, printed below)
    train["ambient"] = {"start_c": 20.0, "drift_c_per_h": 0.08, "daily_amplitude_c": 1.5, "daily_phase_h": 2.0}
    drift = _log(train, tmp_path / "train_drift.csv")
    quiet = _log(yaml.safe_load((SCEN / "lathe_train.yaml").read_text()), tmp_path / "train_quiet.csv")
    unseen = _log(yaml.safe_load((SCEN / "lathe_unseen.yaml").read_text()), tmp_path / "unseen.csv")
    pure, aware = _unseen_rmse(drift, unseen, None), _unseen_rmse(drift, unseen, "T7")
    q_pure, q_aware = _unseen_rmse(quiet, unseen, None), _unseen_rmse(quiet, unseen, "T7")
    print(
        f"unseen-day RMSE, trained with drift: paper {pure:.2f} um, ambient-aware {aware:.2f} um;"
        f" trained in the quiet shop: paper {q_pure:.2f} um, ambient-aware {q_aware:.2f} um"
    )
    assert aware < pure  # measured 1.60 vs 1.86 um
    assert pure < 3.0

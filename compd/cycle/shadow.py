"""The shadow model: a candidate run every cycle beside the active model, driving nothing, scored on the same probes.

A refitted model (or a whole set of contributions) named in the config's `shadow` section
runs in the cycle after the sink has been written: its own inputs checked by the guard's
plausibility rules (a guard of its own on a copy of the frame, whose marks and events stay its
own: a shadow's sensor is not the machine's fault), started on its first good inputs, stepped at its own update period,
predicting from the good inputs where it can, NaN otherwise. Its prediction per axis of the
active model (NaN for an axis it does not serve) is what the status, metrics, telemetry and
data log (`shadow_<axis>_um`) show: the correction it would command is its negative.

Every probe the adapter takes (its whole thermal error, compd.cycle.adapt) scores both on
the same measurement: the active model's prediction and the shadow's, as the two stood
when the probe came. `compd promote CONFIG` moves a shadow that has proven itself into
`model` through the ordinary validated reload (compd/commissioning/promote.py).
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from compd.core.config import GuardConfig
from compd.core.frame import Frame
from compd.cycle.guard import Guard
from compd.models.base import Model, ModelStage


class ShadowScore:
    """Per axis: probes scored, and the sums of squares of what the active and the shadow model left."""

    def __init__(self, axes: list[str]) -> None:
        self.axes = list(axes)
        n = len(axes)
        self.n = [0] * n
        self.active_sq = [0.0] * n
        self.shadow_sq = [0.0] * n
        self.last: list[dict[str, float] | None] = [None] * n

    def add(self, a: int, error_um: float, active_um: float, shadow_um: float, t_s: float) -> None:
        """One measurement of axis `a`'s whole thermal error, against both predictions (skipped unless
        all three are finite)."""
        if not (math.isfinite(error_um) and math.isfinite(active_um) and math.isfinite(shadow_um)):
            return
        self.n[a] += 1
        self.active_sq[a] += (error_um - active_um) ** 2
        self.shadow_sq[a] += (error_um - shadow_um) ** 2
        self.last[a] = {"t_s": t_s, "error_um": error_um, "active_um": active_um, "shadow_um": shadow_um}

    def result(self, a: int) -> dict[str, Any]:
        n = self.n[a]
        act = math.sqrt(self.active_sq[a] / n) if n else None
        sha = math.sqrt(self.shadow_sq[a] / n) if n else None
        return {
            "probes": n,
            "active_rms_um": act,
            "shadow_rms_um": sha,
            "better": None if act is None or sha is None else ("shadow" if sha < act else "active"),
            "last": self.last[a],
        }


class Shadow:
    """The shadow model's stage (see the module); arrays made once, `step` allocates nothing."""

    def __init__(self, model: Model, frame: Frame, guard_cfg: GuardConfig, axes: list[str]) -> None:
        self.model = model
        self.frame = frame
        # its own copy of the frame: its checks mark qualities the active stages never see
        self.view = Frame(frame.names)
        self.guard = Guard(guard_cfg, model.outputs, self.view, model.inputs)
        self.axes = list(axes)
        self.slot = [axes.index(a) for a in model.outputs]  # each shadow output's place among the active axes
        self.x = np.zeros(len(model.inputs))
        self.good = np.zeros(len(model.inputs), dtype=bool)
        self.out = np.full(len(model.outputs), math.nan)
        self.pred_um = np.full(len(axes), math.nan)  # per active axis; NaN where the shadow serves none
        self.stage = ModelStage(model)  # started, stepped and degraded as the active model is
        self.score = ShadowScore(axes)

    def step(self, now_s: float) -> None:
        """This cycle's shadow prediction from the frame (after the active stages ran)."""
        g, view, fr = self.guard, self.view, self.frame
        np.copyto(view.values, fr.values)
        np.copyto(view.quality, fr.quality)
        np.copyto(view.stamp_s, fr.stamp_s)
        ok = g.check_inputs(view, now_s)
        if g.events:
            g.events.clear()  # its inputs' events are not the machine's
        if now_s >= self.stage.next_s:
            np.take(view.values, g.input_idx, out=self.x)
            if not ok:
                np.equal(view.quality[g.input_idx], 0, out=self.good)
            self.stage.step(self.x, self.good, ok, now_s, self.out)
        for j, a in enumerate(self.slot):
            self.pred_um[a] = self.out[j]

    def probed(self, probe_um: np.ndarray, active_um: np.ndarray, t_s: float) -> None:
        """Probes came this cycle (their whole errors per axis, NaN where none): score both models."""
        for a in range(len(self.axes)):
            z = float(probe_um[a])
            if math.isfinite(z):
                self.score.add(a, z, float(active_um[a]), float(self.pred_um[a]), t_s)

    def get_status(self) -> dict[str, Any]:
        """The shadow model (kind, file, which one it is, fit date) and its score against the active one per
        axis it serves (the score is of this shadow: `compd promote` compares its sha256 with the config's)."""
        fit = self.model.fit_info
        return {
            "model": {
                "kind": self.model.kind,
                "file": self.model.file,
                "sha256": self.model.sha256,
                "inputs": self.model.inputs,
                "outputs": self.model.outputs,
                "fitted_at": fit.get("fitted_at"),
            },
            "axes": {self.axes[a]: self.score.result(a) for a in self.slot},
        }

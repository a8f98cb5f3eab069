"""Latent-variable regression (PLS) on temperature rises (paper 002); the fit chooses components by blocked cross-validation (or the paper's LOO Q²).

The PLS fit and its component selection (blocked cross-validation over stretches of the
log, or paper 002's exact fast leave-one-out Q²) are in compd.identify.lvr; the fitted
model evaluates the same linear form as MLR (compd.models.mlr.RiseLinear).
"""

from __future__ import annotations

from typing import TYPE_CHECKING

from pydantic import Field

from compd.core.errors import BadInput
from compd.models.mlr import RiseLinear, RiseLinearParams

if TYPE_CHECKING:
    import numpy as np

    from compd.identify.lvr import PLSModel


def fit_pls(X: np.ndarray, Y: np.ndarray, n_components: int) -> PLSModel:
    """PLS regression with `n_components` components: `coef_` (p × q, original units), `predict(X)` (n × q).

    Implemented in compd.identify.lvr (imported on call, so this module stays light).
    """
    from compd.identify.lvr import fit_pls as fit

    return fit(X, Y, n_components)


class LVRParams(RiseLinearParams):
    """LVR run-time params: the linear form plus how many components it was built from."""

    n_components: int = Field(ge=1, description="PLS components the coefficients come from (≤ inputs)")


class LVR(RiseLinear):
    """PLS model on temperature rises (paper 002)."""

    kind = "lvr"
    summary_keys = ("n_components", "coef_um_per_k", "intercept_um")
    per_axis_keys = ("intercept_um",)
    Params = LVRParams
    params: LVRParams

    @classmethod
    def check_wiring(cls, params, inputs, outputs) -> None:
        super().check_wiring(params, inputs, outputs)
        if params.n_components > len(inputs):
            raise BadInput(
                f"{params.n_components} components from {len(inputs)} inputs: at most one per input",
                path=("params", "n_components"),
            )

"""The axes the machine is driven on are declared once (the sink's `axes`, `codec.axes`, else the first
model's outputs): a model, contribution or shadow output, or a per-axis key, naming another is refused
with "did you mean" — a typo never becomes an axis of its own that drives the word's other byte."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from compd.cli import main
from compd.config import load_config
from compd.core.errors import ConfigError
from compd.daemon.run import reload
from compd.log import write_log


def _mlr(outputs: str, n: int = 1) -> str:
    zeros = ", ".join(["0.0"] * n)
    return (
        f"{{kind: mlr, inputs: [T1], outputs: {outputs}, params: {{intercept_um: [{zeros}],"
        f" coef_um_per_k: [[{zeros}]], t0_c: [20.0]}}}}"
    )


def _config(tmp_path: Path, model: str, more: str = "", sink: str = "{kind: fanuc_pmc}") -> Path:
    if not (tmp_path / "day.csv").exists():
        t = np.arange(10, dtype=float)
        write_log(tmp_path / "day.csv", ["t_s", "T1", "pos_z_mm"], np.column_stack([t, 20.0 + t, t]))
    p = tmp_path / "axes.yaml"
    p.write_text(f"""\
loop: {{clock: sim, period_s: 1.0}}
sources:
  - {{kind: replay, name: log, path: day.csv}}
model:
{model}
sink: {sink}
{more}""")
    return p


def _line_of(path: Path, text: str) -> int:
    return next(i for i, line in enumerate(path.read_text().splitlines(), 1) if text in line)


TYPO = f"""\
  contributions:
    - {{name: spindle, {_mlr("[z]")[1:]}
    - {{name: column, {_mlr("[Z]")[1:]}
"""


def test_a_contribution_on_a_misspelt_axis_is_refused_with_did_you_mean(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """Issue 39 item 6: `outputs: [Z]` beside `z` made the word's second axis; now one line naming the
    file, the line of the entry and its key path, exit 2."""
    cfg = _config(tmp_path, TYPO)
    capsys.readouterr()
    assert main(["check-config", str(cfg)]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1, err
    assert f"{cfg}:{_line_of(cfg, 'name: column')}: model.contributions[1].outputs[0]:" in err
    assert "'Z' is not an axis the sink drives (z: the outputs of model.contributions[0]" in err
    assert err.endswith("did you mean 'z'?")
    # compd run refuses it the same way, before opening anything
    assert main(["run", str(cfg), "--duration", "1"]) == 2
    assert "did you mean 'z'?" in capsys.readouterr().err


def test_a_reload_to_a_misspelt_axis_is_rejected(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    running = object()  # the App that goes on: a rejected reload never touches it
    cfg = _config(tmp_path, TYPO)
    capsys.readouterr()
    assert reload(running, str(cfg), None, None) is running
    err = capsys.readouterr().err
    assert "reload rejected" in err and "model.contributions[1].outputs[0]" in err and "did you mean 'z'?" in err


def test_a_model_file_with_a_misspelt_axis_is_named_in_its_file(tmp_path: Path) -> None:
    (tmp_path / "column.yaml").write_text(
        "kind: mlr\ninputs: [T1]\noutputs: [Z]\nparams: {intercept_um: [0.0], coef_um_per_k: [[0.0]], t0_c: [20.0]}\n"
    )
    model = f"""\
  contributions:
    - {{name: spindle, {_mlr("[z]")[1:]}
    - {{name: column, kind: mlr, file: column.yaml}}
"""
    with pytest.raises(ConfigError) as e:
        load_config(_config(tmp_path, model))
    err = str(e.value)
    assert err.startswith(f"{tmp_path / 'column.yaml'}:3: outputs[0]: 'Z' is not an axis the sink drives"), err
    assert "(the model file of model.contributions[1]); did you mean 'z'?" in err


def test_contributions_on_two_axes_need_them_declared(tmp_path: Path) -> None:
    """A lathe's z and x from two contributions: codec.axes declares both; without it the first
    contribution's outputs are the axes, and the error says codec.axes declares more."""
    model = f"""\
  contributions:
    - {{name: spindle, {_mlr("[z]")[1:]}
    - {{name: cross, {_mlr("[x]")[1:]}
"""
    with pytest.raises(ConfigError, match=r"'x' is not an axis the sink drives \(z: .*codec.axes declares more\)$"):
        load_config(_config(tmp_path, model))
    cfg = load_config(_config(tmp_path, model, "codec: {axes: [z, x]}"))
    assert cfg.model.outputs == ["z", "x"]


def test_codec_axes_declare_the_axes_for_a_single_model(tmp_path: Path) -> None:
    with pytest.raises(ConfigError) as e:
        load_config(_config(tmp_path, "  " + _mlr("[Z]"), "codec: {axes: [z]}"))
    assert e.value.path == "model.outputs[0]"
    assert "'Z' is not an axis the sink drives (z: codec.axes); did you mean 'z'?" in str(e.value)


def test_the_siemens_axes_declare_the_axes_it_drives(tmp_path: Path) -> None:
    """A model output the NC section does not map reached no NC axis, silently: now refused."""
    sink = "{kind: siemens, axes: {z: 0}}"
    with pytest.raises(ConfigError) as e:
        load_config(_config(tmp_path, "  " + _mlr("[z, x]", 2), "codec: {axes: [z, x]}", sink=sink))
    assert "'x' is not an axis the sink drives (z: sink.axes)" in str(e.value)
    assert load_config(_config(tmp_path, "  " + _mlr("[z]"), sink=sink)).model.outputs == ["z"]


@pytest.mark.parametrize(
    ("more", "key"),
    [
        ("guard: {axes: {Z: {max_abs_um: 10}}}", "guard.axes.Z"),
        ("inhibit: {axes: {Z: {signal: T1}}}", "inhibit.axes.Z"),
        ("adapt: {slope_position: {Z: pos_z_mm}}", "adapt.slope_position.Z"),
        ("shadow: " + _mlr("[Z]"), "shadow.outputs[0]"),
    ],
)
def test_every_key_that_names_an_axis_says_did_you_mean(tmp_path: Path, more: str, key: str) -> None:
    cfg = _config(tmp_path, "  " + _mlr("[z]"), more)
    with pytest.raises(ConfigError) as e:
        load_config(cfg)
    assert e.value.path == key and e.value.line == _line_of(cfg, more.split(":")[0] + ":")
    assert str(e.value).endswith("did you mean 'z'?"), str(e.value)


def test_axis_names_stay_as_written(tmp_path: Path) -> None:
    """Case-sensitive: an upper-case axis declared once is that axis, never lower-cased."""
    model = f"""\
  contributions:
    - {{name: a, {_mlr("[Z]")[1:]}
    - {{name: b, {_mlr("[Z]")[1:]}
"""
    cfg = load_config(_config(tmp_path, model, "guard: {axes: {Z: {max_abs_um: 10}}}"))
    assert cfg.model.outputs == ["Z"]

"""Config validation: every error names file, line and key path; exit 2 from the CLI."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

from compd.cli import main
from compd.config import load_config
from compd.core.errors import ConfigError
from compd.daemon.app import App

ROOT = Path(__file__).resolve().parents[2]
CONFIGS = sorted((ROOT / "configs").glob("*.yaml"))

GOOD = """\
loop:
  clock: sim
  period_s: 0.1
sources:
  - kind: sim
    name: spindle
    plant: spindle
    scenario:
      segments: [{duration_s: 600, speed_rpm: 8000}]
model:
  kind: xi_spindle
  inputs: [T_xi]
  outputs: [z]
  params: {alpha_per_k: 13.6e-6, length_mm: 165.0}
guard:
  max_slew_um_per_s: 2.0
sink:
  kind: pci1756
"""


def write(tmp_path: Path, text: str) -> Path:
    p = tmp_path / "c.yaml"
    p.write_text(text)
    return p


def error_for(tmp_path: Path, text: str) -> ConfigError:
    p = write(tmp_path, text)
    with pytest.raises(ConfigError) as ei:
        App(load_config(p))
    return ei.value


def test_good_config_loads(tmp_path: Path) -> None:
    cfg = load_config(write(tmp_path, GOOD))
    assert cfg.loop.period_s == 0.1
    assert cfg.model.inputs == ["T_xi"]
    app = App(cfg)
    assert app.frame.names[:2] == ["T_xi", "T_amb"] and "err_z_um" in app.frame.names


def test_misspelt_key_names_key_and_line(tmp_path: Path) -> None:
    e = error_for(tmp_path, GOOD.replace("max_slew_um_per_s", "max_slew_um_per_sec"))
    assert e.line == 16
    assert e.path == "guard.max_slew_um_per_sec"
    assert "unknown key" in str(e) and "max_slew_um_per_s" in str(e)
    assert str(e).startswith(f"{e.file}:16: guard.max_slew_um_per_sec:")


def test_wrong_type(tmp_path: Path) -> None:
    e = error_for(tmp_path, GOOD.replace("period_s: 0.1", "period_s: fast"))
    assert e.line == 3 and e.path == "loop.period_s"


def test_negative_period(tmp_path: Path) -> None:
    e = error_for(tmp_path, GOOD.replace("period_s: 0.1", "period_s: -0.002"))
    assert e.path == "loop.period_s" and "greater than or equal to 0.0005" in e.message


def test_lsb_not_positive(tmp_path: Path) -> None:
    e = error_for(tmp_path, GOOD + "codec:\n  lsb_um: 0\n")
    assert e.path == "codec.lsb_um" and e.line == 20


def test_unknown_source_kind_lists_known(tmp_path: Path) -> None:
    e = error_for(tmp_path, GOOD.replace("kind: sim", "kind: simulator"))
    assert e.path == "sources[0].kind" and e.line == 5
    assert "sim" in e.message and "replay" in e.message


def test_unknown_model_kind(tmp_path: Path) -> None:
    e = error_for(tmp_path, GOOD.replace("kind: xi_spindle", "kind: xi"))
    assert e.path == "model.kind" and "xi_spindle" in e.message


def test_unknown_key_inside_source(tmp_path: Path) -> None:
    e = error_for(tmp_path, GOOD.replace("plant: spindle", "plant: spindle\n    plnat: x"))
    assert e.path == "sources[0].plnat" and e.line == 8


def test_a_misspelt_required_key_is_named_as_written_with_the_key_it_stands_for(tmp_path: Path) -> None:
    e = error_for(tmp_path, GOOD.replace("plant: spindle", "plnat: spindle"))
    assert e.path == "sources[0].plnat" and e.line == 7
    assert "did you mean 'plant'?" in e.message


def test_unknown_key_inside_model_params(tmp_path: Path) -> None:
    e = error_for(tmp_path, GOOD.replace("length_mm: 165.0", "length_mm: 165.0, lenght: 3"))
    assert e.path == "model.params.lenght" and e.line == 14


def test_missing_section(tmp_path: Path) -> None:
    e = error_for(tmp_path, GOOD.replace("sink:\n  kind: pci1756\n", ""))
    assert e.path == "sink" and "missing" in e.message


def test_model_input_not_a_signal(tmp_path: Path) -> None:
    e = error_for(tmp_path, GOOD.replace("inputs: [T_xi]", "inputs: [T_nose]"))
    assert "T_nose" in e.message and "T_xi" in e.message
    assert e.path == "model.inputs"


def test_yaml_syntax_error_has_line(tmp_path: Path) -> None:
    e = error_for(tmp_path, GOOD.replace("  period_s: 0.1", "  period_s: [0.1"))
    assert e.line is not None and "YAML" in e.message


def test_duplicate_key(tmp_path: Path) -> None:
    e = error_for(tmp_path, GOOD.replace("  period_s: 0.1", "  period_s: 0.1\n  period_s: 0.2"))
    assert e.path == "loop.period_s" and e.line == 4 and "duplicate" in e.message


def test_heartbeat_inside_word_rejected(tmp_path: Path) -> None:
    e = error_for(tmp_path, GOOD.replace("kind: pci1756", "kind: pci1756\n  heartbeat_bit: 3"))
    assert e.path == "sink" and "heartbeat" in e.message


def test_empty_and_missing_file(tmp_path: Path) -> None:
    with pytest.raises(ConfigError, match="empty"):
        load_config(write(tmp_path, ""))
    with pytest.raises(ConfigError, match="cannot read"):
        load_config(tmp_path / "nope.yaml")


def test_check_config_cli_exit_codes(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    p = write(tmp_path, GOOD)
    assert main(["check-config", str(p)]) == 0
    assert capsys.readouterr().out.strip() == "ok"
    p.write_text(GOOD.replace("clock: sim", "clok: sim"))
    assert main(["check-config", str(p)]) == 2
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0
    assert f"{p}:2: loop.clok: unknown key" in err


def test_run_cli_bad_config_exits_2(tmp_path: Path) -> None:
    p = write(tmp_path, GOOD.replace("clock: sim", "clock: lunar"))
    r = subprocess.run([sys.executable, "-m", "compd", "run", str(p)], capture_output=True, text=True)
    assert r.returncode == 2
    assert "loop.clock" in r.stderr and ":2:" in r.stderr
    assert "Traceback" not in r.stderr


@pytest.mark.parametrize("path", CONFIGS, ids=[p.name for p in CONFIGS])
def test_every_example_config_checks(path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["check-config", str(path)]) == 0, capsys.readouterr().err

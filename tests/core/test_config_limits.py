"""Hostile YAML never hangs or crashes `compd check-config`: one line, exit 2, the file named.

Each input runs through the CLI in a subprocess; the 20 s timeout is the hang detector
(all of these are refused in well under a second), not a speed assertion.
"""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

from compd.config import load_config, load_model_file
from compd.core.config import (
    CONFIG_MAX_BYTES,
    CONFIG_MAX_VALUES,
    MAX_ALIAS_VALUES,
    MAX_DEPTH,
    MODEL_MAX_BYTES,
    load_yaml,
)
from compd.core.errors import ConfigError
from tests.conftest import ROOT

LAUGHS = "a: &a [lol, lol, lol, lol, lol, lol, lol, lol, lol]\n" + "".join(
    f"{n}: &{n} [{', '.join([f'*{p}'] * 9)}]\n" for p, n in zip("abcdefgh", "bcdefghi", strict=True)
)
MERGE_BOMB = "a: &a {k0: 0, k1: 1, k2: 2, k3: 3, k4: 4, k5: 5, k6: 6, k7: 7, k8: 8}\n" + "".join(
    f"{n}: &{n} {{<<: [{', '.join([f'*{p}'] * 9)}], x: {{<<: [{', '.join([f'*{p}'] * 9)}]}}}}\n"
    for p, n in zip("abcdefgh", "bcdefghi", strict=True)
)


def check_config(path: str | Path) -> subprocess.CompletedProcess[str]:
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    return subprocess.run(
        [sys.executable, "-m", "compd", "check-config", str(path)],
        capture_output=True,
        text=True,
        timeout=20,
        env=env,
        stdin=subprocess.DEVNULL,
    )


def assert_refused(r: subprocess.CompletedProcess[str], path: str | Path, *words: str) -> None:
    lines = r.stderr.strip().splitlines()
    assert r.returncode == 2, r.stderr[-2000:]
    assert len(lines) == 1 and "Traceback" not in r.stderr, r.stderr[-2000:]
    assert str(path) in lines[0]
    for w in words:
        assert w in lines[0], lines[0]


@pytest.mark.parametrize(
    ("name", "text", "words"),
    [
        ("billion_laughs", LAUGHS, ("alias",)),
        ("merge_bomb", MERGE_BOMB, ("alias",)),
        ("deep_flow", "[" * 10_000 + "\n", ("nested", ":1:")),
        ("deep_flow_200k", "[" * 200_000 + "\n", ("nested",)),  # libyaml's own composer segfaults here
        ("deep_block", "".join(" " * i + "- \n" for i in range(0, 400, 2)) + " " * 400 + "- 1\n", ("nested",)),
        ("self_alias", "a: &a [1, *a]\n", ("nested",)),
        ("many_values", "a: [" + "0," * (CONFIG_MAX_VALUES + 10) + "0]\n", ("values",)),
        ("too_big", "# " + "x" * CONFIG_MAX_BYTES + "\n", ("bytes",)),
        ("huge_int", "loop: {period_s: " + "9" * 5000 + "}\n", (":1:",)),
        ("two_documents", "loop: {}\n---\nloop: {}\n", (":2:", "document")),
    ],
)
def test_hostile_yaml_is_refused(tmp_path: Path, name: str, text: str, words: tuple[str, ...]) -> None:
    p = tmp_path / f"{name}.yaml"
    p.write_text(text)
    assert_refused(check_config(p), p, *words)


def test_dev_zero_is_refused() -> None:
    assert_refused(check_config("/dev/zero"), "/dev/zero", "not a regular file")


def test_fifo_without_writer_is_refused(tmp_path: Path) -> None:
    p = tmp_path / "fifo.yaml"
    os.mkfifo(p)
    assert_refused(check_config(p), p, "not a regular file")


def test_directory_is_refused(tmp_path: Path) -> None:
    assert_refused(check_config(tmp_path), tmp_path, "directory")


def test_model_file_gets_the_same_protection(tmp_path: Path) -> None:
    model = tmp_path / "m.yaml"
    model.write_text(LAUGHS)
    cfg = tmp_path / "c.yaml"
    cfg.write_text(
        "loop: {clock: sim, period_s: 0.1}\n"
        "sources: [{kind: sim, name: s, plant: spindle, scenario: {segments: [{duration_s: 60}]}}]\n"
        f"model: {{kind: xi_spindle, file: {model}}}\n"
        "sink: {kind: pci1756}\n"
    )
    with pytest.raises(ConfigError, match="alias"):
        load_model_file(model)
    assert_refused(check_config(cfg), model, "alias")
    model.write_text("kind: xi_spindle\n" + "#" * MODEL_MAX_BYTES + "\n")
    with pytest.raises(ConfigError, match="bytes"):
        load_model_file(model)


def test_limits_leave_room_for_real_files() -> None:
    """Merges and a few aliases work; the limits are far above what the examples use."""
    doc = load_yaml("x.yaml", text="base: &b {k: 1, m: 2}\nuse:\n  <<: *b\n  k: 3\nlist: [*b, *b]\n")
    assert doc.data["use"] == {"k": 3, "m": 2} and doc.data["list"] == [{"k": 1, "m": 2}] * 2
    assert doc.lines[("use", "k")] == 4
    for path in sorted((ROOT / "configs").glob("*.yaml")):
        assert path.stat().st_size < CONFIG_MAX_BYTES // 100
        load_config(path)
    assert MAX_DEPTH >= 32 and MAX_ALIAS_VALUES >= 1000


def test_replay_source_on_a_device_is_refused(tmp_path: Path) -> None:
    """check-config builds the sources: a replay log that is /dev/zero must not hang it."""
    cfg = tmp_path / "c.yaml"
    cfg.write_text(
        "loop: {clock: sim, period_s: 0.1}\n"
        "sources: [{kind: replay, name: r, path: /dev/zero}]\n"
        "model: {kind: xi_spindle, inputs: [T_xi], outputs: [z], params: {alpha_per_k: 1.0e-5, length_mm: 100}}\n"
        "sink: {kind: pci1756}\n"
    )
    assert_refused(check_config(cfg), "/dev/zero", "not a regular file")


def test_a_parser_depth_limit_reads_as_nesting(monkeypatch: pytest.MonkeyPatch) -> None:
    """Some libyaml builds stop deep nesting in the parser itself, before compd's MAX_DEPTH:
    the one-line error still says the document is nested too deep, with its line."""
    import yaml

    import compd.core.config as config

    class DepthLimitedLoader(yaml.SafeLoader):
        def get_event(self) -> yaml.Event:
            raise yaml.parser.ParserError(
                None, None, "exceeded maximum nesting depth", yaml.Mark("f", 0, 0, 0, None, None)
            )

    monkeypatch.setattr(config, "_Loader", DepthLimitedLoader)
    with pytest.raises(ConfigError) as e:
        load_yaml("deep.yaml", text="[[[[\n")
    assert "nested deeper" in str(e.value) and "deep.yaml:1" in str(e.value)

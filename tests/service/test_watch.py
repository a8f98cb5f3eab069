"""`compd status --watch`: redraws per axis and per signal, waits for a daemon, stops on Ctrl-C."""

from __future__ import annotations

import io
import time

import pytest

from compd.cli import main
from compd.config import load_config
from compd.daemon.app import App
from compd.service import watch as watch_mod
from compd.service.status import snapshot, write_atomic
from compd.service.watch import watch
from tests.service_helpers import sim_config


@pytest.fixture(scope="module")
def snap(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("watch")
    app = App(load_config(sim_config(tmp, duration_s=600)))
    app.run()
    return snapshot(app.loop, state="running", observe=False)


def _live(path, snap, **kw):
    write_atomic(path, {**snap, "status_period_s": 1.0, "written_unix_s": time.time(), **kw})


def test_waits_while_no_daemon_runs_then_shows_it(tmp_path, snap):
    path = tmp_path / "status.json"
    out = io.StringIO()
    sleeps: list[float] = []

    def sleep(s):  # the daemon comes up between the first and the second frame
        sleeps.append(s)
        _live(path, snap)

    rc = watch(str(path), 0.5, out=out, use_rich=False, frames=2, sleep=sleep)
    text = out.getvalue()
    first, second = text.split("compd status --watch")[1:]
    assert "not running: no status file" in first and "waiting for the daemon" in first
    assert "compd running" in second
    assert any(ln.startswith("z ") and "normal" in ln for ln in second.splitlines())  # per axis
    assert any(ln.startswith("T_xi ") and "good" in ln for ln in second.splitlines())  # per signal
    assert sleeps == [0.5] and rc == 0


def test_a_stopped_daemon_is_said_and_the_code_is_status_s(tmp_path, snap):
    path = tmp_path / "status.json"
    _live(path, snap, state="stopped")
    out = io.StringIO()
    assert watch(str(path), 1.0, out=out, use_rich=False, frames=1) == 1
    assert "NOT RUNNING: stopped" in out.getvalue()


def test_ctrl_c_ends_it_cleanly(tmp_path, snap, monkeypatch, capsys):
    path = tmp_path / "status.json"
    _live(path, snap)

    def interrupt(s):
        raise KeyboardInterrupt

    monkeypatch.setattr(watch_mod.time, "sleep", interrupt)
    assert main(["status", "--status", str(path), "--watch", "--interval-s", "0.2"]) == 0
    cap = capsys.readouterr()
    assert "compd running" in cap.out and cap.err == ""


def test_bad_arguments_exit_2(tmp_path, capsys):
    path = str(tmp_path / "status.json")
    assert main(["status", "--status", path, "--watch", "--json"]) == 2
    assert "--watch" in capsys.readouterr().err
    for bad in ("0", "-1", "nan"):
        with pytest.raises(SystemExit) as e:
            main(["status", "--status", path, "--watch", "--interval-s", bad])
        assert e.value.code == 2


def test_rich_view_has_a_table_per_axis_and_signal(tmp_path, snap):
    pytest.importorskip("rich")
    path = tmp_path / "status.json"
    _live(path, snap)
    out = io.StringIO()
    calls = []
    rc = watch(str(path), 1.0, out=out, use_rich=True, frames=2, sleep=calls.append)
    text = out.getvalue()
    assert rc == 0 and calls == [1.0]
    assert "axes" in text and "signals" in text and "policy" in text
    assert "T_xi" in text and "good" in text and "normal" in text


def test_a_malformed_status_file_is_said_not_a_traceback(tmp_path, snap):
    path = tmp_path / "status.json"
    _live(path, snap, model={"kind": "mlr", "fit": ["not", "a", "mapping"]})
    out = io.StringIO()
    assert watch(str(path), 1.0, out=out, use_rich=False, frames=1) == 1
    assert "not a compd status file: AttributeError" in out.getvalue()
    path.write_text("{", encoding="utf-8")
    out = io.StringIO()
    assert watch(str(path), 1.0, out=out, use_rich=False, frames=1) == 1
    assert "not running: not a status file" in out.getvalue()


def test_a_source_s_last_error_is_shown(tmp_path, snap):
    path = tmp_path / "status.json"
    sources = [
        {
            "kind": "dcon",
            "name": "adam",
            "last_error": "open: could not open port /dev/ttyUSB9: [Errno 2] No such file or directory",
        },
        {"kind": "replay", "name": "log"},
    ]
    _live(path, snap, sources=sources)
    for use_rich in (False, True):
        if use_rich:
            pytest.importorskip("rich")
        out = io.StringIO()
        watch(str(path), 1.0, out=out, use_rich=use_rich, frames=1)
        text = " ".join(out.getvalue().split())
        assert "source adam (dcon): last error: open: could not open port /dev/ttyUSB9" in text
        assert "source log" not in text

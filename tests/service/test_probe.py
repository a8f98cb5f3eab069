"""`compd probe` and the daemon's probe socket (compd/service/control.py), with the daemon as a real process."""

from __future__ import annotations

import contextlib
import io
import json
import logging
import math
import os
import signal
import socket
import stat
import subprocess
import sys
import time
from pathlib import Path

import pytest

from compd.core.errors import BadInput
from compd.service import control
from tests.service_helpers import sim_config

ROOT = Path(__file__).resolve().parents[2]
ENV = {**os.environ, "PYTHONPATH": str(ROOT)}
WAIT_S = 60.0  # an upper bound for a condition to become true, never a sleep

EXTRA = """
status: {{path: status.json, period_s: 0.1}}
log: {{path: log.csv, period_s: 10}}
state: {{path: state.json}}
adapt: {{}}
"""


def compd(*args: str, cwd: Path, timeout: float = 30) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, "-m", "compd", *args], cwd=cwd, env=ENV, capture_output=True, text=True, timeout=timeout
    )


def until(cond, what: str, timeout: float = WAIT_S):
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        v = cond()
        if v:
            return v
        time.sleep(0.05)
    raise AssertionError(f"timed out waiting for {what}")


def status_of(folder: Path) -> dict:
    try:
        return json.loads((folder / "status.json").read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return {}


def stale_socket(path: Path) -> None:
    """What a crashed daemon leaves: a socket file nobody listens on."""
    s = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    s.bind(str(path))
    s.close()


@pytest.fixture
def daemon(tmp_path):
    """A daemon on the simulated spindle (paced: 50× real time), stopped with SIGTERM at the end."""
    cfg = sim_config(tmp_path, EXTRA.format(), duration_s=1e6, speedup=50)
    stale_socket(tmp_path / "status.sock")  # a crashed daemon's: the new one must replace it
    proc = subprocess.Popen(
        [sys.executable, "-m", "compd", "run", cfg.name],
        cwd=tmp_path,
        env=ENV,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    try:
        until(lambda: status_of(tmp_path).get("state") == "running" or proc.poll() is not None, "the daemon")
        assert proc.poll() is None, proc.communicate()
        yield proc, cfg
    finally:
        if proc.poll() is None:
            proc.send_signal(signal.SIGTERM)
        try:
            proc.communicate(timeout=30)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.communicate()


def test_probe_reaches_the_daemon_which_logs_shows_and_keeps_it(daemon, tmp_path):
    proc, cfg = daemon
    sock = tmp_path / "status.sock"
    assert stat.S_IMODE(sock.stat().st_mode) == 0o660
    until(lambda: (status_of(tmp_path).get("axes") or {}).get("z", {}).get("prediction_um") is not None, "a prediction")

    r = compd("probe", "--config", cfg.name, "--axis", "z", "--error-um", "3.5", "--position-mm", "120", cwd=tmp_path)
    assert r.returncode == 0, r.stderr
    assert len(r.stdout.splitlines()) == 1 and "probe z error 3.5 um" in r.stdout
    assert any(w in r.stdout for w in ("accepted", "rejected", "queued"))

    # an unknown axis: the daemon knows its axes and answers with an error (exit 2, one line)
    r = compd("probe", "--config", cfg.name, "--axis", "q", "--error-um", "1", cwd=tmp_path)
    assert r.returncode == 2 and len(r.stderr.splitlines()) == 1 and "unknown axis 'q'" in r.stderr
    # a non-finite error never leaves the command line
    r = compd("probe", "--config", cfg.name, "--axis", "z", "--error-um", "inf", cwd=tmp_path)
    assert r.returncode == 2 and len(r.stderr.splitlines()) == 1 and "finite" in r.stderr

    def taken():
        z = (status_of(tmp_path).get("adapt") or {}).get("z") or {}
        return z if z.get("accepted", 0) + z.get("rejected", 0) else None

    adapt = until(taken, "the probe in the status")
    assert adapt["accepted"] + adapt["rejected"] == 1
    shown = compd("status", "--config", cfg.name, cwd=tmp_path)
    assert shown.returncode == 0 and "adapt" in shown.stdout and "±" in shown.stdout

    proc.send_signal(signal.SIGTERM)
    out, err = proc.communicate(timeout=30)
    assert proc.returncode == 0, err
    assert "event=probe_accepted" in err or "event=probe_rejected" in err
    assert not sock.exists()  # removed at shutdown

    header, *rows = (tmp_path / "log.csv").read_text(encoding="utf-8").splitlines()
    cols = header.split(",")
    assert cols[-2:] == ["probe_z_um", "probe_pos_z_mm"]
    probed = [r.split(",") for r in rows if r.split(",")[-2] != ""]
    assert len(probed) == 1 and float(probed[0][-2]) == 3.5 and float(probed[0][-1]) == 120.0

    saved = json.loads((tmp_path / "state.json").read_text(encoding="utf-8"))
    z = saved["adapt"]["axes"]["z"]
    assert z["accepted"] + z["rejected"] == 1 and saved["adapt"]["params_sha256"]

    # after the daemon: nothing answers (the socket is gone): exit 1, one line
    r = compd("probe", "--config", cfg.name, "--axis", "z", "--error-um", "1", cwd=tmp_path)
    assert r.returncode == 1 and len(r.stderr.splitlines()) == 1 and "no compd running" in r.stderr


def run_briefly(tmp_path: Path, cfg: Path) -> tuple[str, dict]:
    r = compd("run", cfg.name, "--duration", "5", cwd=tmp_path, timeout=60)
    assert r.returncode == 0, r.stderr
    return r.stderr, status_of(tmp_path)


def test_the_estimate_is_restored_for_the_same_model_and_reset_for_a_refit_one(tmp_path):
    cfg = sim_config(tmp_path, EXTRA.format(), duration_s=1e6, speedup=0)
    saved = {
        "format": 1,
        "kind": "xi_spindle",
        "inputs": ["T_xi"],
        "outputs": ["z"],
        "saved_unix_s": time.time(),
        "state": {"t0_c": 19.8, "ref_c": None},
    }
    from compd.config import load_config
    from compd.service.state import params_digest

    digest = params_digest(load_config(cfg).model.params)
    axes = {"z": {"s": [2.5], "P": [[0.04]], "t_probe_s": 10.0, "accepted": 4, "rejected": 1, "probe_age_s": 30.0}}
    (tmp_path / "state.json").write_text(
        json.dumps({**saved, "adapt": {"params_sha256": digest, "saved_unix_s": time.time(), "axes": axes}}),
        encoding="utf-8",
    )
    err, st = run_briefly(tmp_path, cfg)
    assert "event=adapt_restored" in err
    assert st["adapt"]["z"]["accepted"] == 4 and st["adapt"]["z"]["offset_um"] == pytest.approx(2.5)
    kept = json.loads((tmp_path / "state.json").read_text(encoding="utf-8"))["adapt"]
    assert kept["params_sha256"] == digest and kept["axes"]["z"]["accepted"] == 4

    # the same model refitted (other params): the estimate starts again from zero
    cfg.write_text(cfg.read_text(encoding="utf-8").replace("13.6e-6", "14.1e-6"), encoding="utf-8")
    err, st = run_briefly(tmp_path, cfg)
    assert "event=adapt_reset" in err
    assert st["adapt"]["z"]["accepted"] == 0 and st["adapt"]["z"]["offset_um"] == 0.0
    kept = json.loads((tmp_path / "state.json").read_text(encoding="utf-8"))["adapt"]
    assert kept["params_sha256"] != digest and kept["axes"]["z"]["accepted"] == 0


def test_no_daemon_and_a_stale_socket_exit_1_at_once(tmp_path):
    cfg = sim_config(tmp_path, EXTRA.format())
    r = compd("probe", "--config", cfg.name, "--axis", "z", "--error-um", "1", cwd=tmp_path)
    assert r.returncode == 1 and len(r.stderr.splitlines()) == 1 and "no probe socket" in r.stderr
    stale_socket(tmp_path / "status.sock")
    r = compd("probe", "--config", cfg.name, "--axis", "z", "--error-um", "1", cwd=tmp_path)
    assert r.returncode == 1 and len(r.stderr.splitlines()) == 1 and "refuses connections" in r.stderr
    # refused at once, not after a timeout: with an hour's timeout it still returns
    with pytest.raises(control.NoDaemon, match="refuses connections"):
        control.send_probe(tmp_path / "status.sock", {"op": "probe"}, timeout_s=3600)


def test_bad_input_exits_2_with_one_line(tmp_path):
    no_adapt = sim_config(tmp_path)
    r = compd("probe", "--config", no_adapt.name, "--axis", "z", "--error-um", "1", cwd=tmp_path)
    assert r.returncode == 2 and len(r.stderr.splitlines()) == 1 and "adapt" in r.stderr
    for args in (
        ["--axis", "z", "--error-um", "nan"],
        ["--axis", "z"],
        ["--axis", "z", "--error-um", "1", "--sigma-um", "0"],
    ):
        r = compd("probe", *args, cwd=tmp_path)
        assert r.returncode == 2 and len(r.stderr.splitlines()) == 1, (args, r.stderr)


class FakeLink(control.ProbeLink):
    """What the socket's thread reaches: where probes go, and the verdicts that come back."""

    def __init__(self, verdicts: bool = False) -> None:
        self.sent: list = []
        self.verdicts = verdicts

    @property
    def axes(self) -> list[str]:
        return ["x", "z"]

    def send(self, probe) -> None:  # noqa: ANN001
        self.sent.append(probe)

    def outcome(self, tag: str) -> dict | None:
        if not self.verdicts or not self.sent or self.sent[-1].source != tag:
            return None
        return {"event": "accepted", "source": tag, "t_s": 42.0, "offset_um": float("nan")}


def test_server_queues_the_probe_and_answers_queued_when_no_cycle_takes_it(tmp_path, monkeypatch):
    monkeypatch.setattr(control, "WAIT_S", 0.05)
    link = FakeLink()
    server = control.ControlServer(tmp_path / "c.sock")
    server.open()
    server.serve(link)
    try:
        with pytest.raises(BadInput, match="another compd serves"):
            control.ControlServer(tmp_path / "c.sock").open()
        answer = control.send_probe(
            tmp_path / "c.sock", {"op": "probe", "axis": "x", "error_um": 4.0, "position_mm": 3.0, "residual": True}
        )
        assert answer["ok"] and answer["outcome"] == "queued" and answer["t_s"] is None
        assert answer["pid"] == os.getpid()
        (probe,) = link.sent
        assert (probe.axis, probe.error_um, probe.position_mm, probe.residual) == ("x", 4.0, 3.0, True)
        assert math.isnan(probe.t_s)  # the cycle stamps it when it takes it
        link.verdicts = True
        answer = control.send_probe(tmp_path / "c.sock", {"op": "probe", "axis": "z", "error_um": 1.0})
        assert answer["outcome"] == "accepted" and answer["t_s"] == 42.0 and answer["offset_um"] is None
        bad = control.send_probe(tmp_path / "c.sock", {"op": "probe", "axis": "x", "error_um": "1"})
        assert not bad["ok"] and "finite" in bad["error"]
    finally:
        server.close()
    assert not (tmp_path / "c.sock").exists()


def test_a_path_that_is_not_a_socket_is_refused(tmp_path):
    (tmp_path / "c.sock").write_text("x", encoding="utf-8")
    with pytest.raises(BadInput, match="not a socket"):
        control.ControlServer(tmp_path / "c.sock").open()


def test_a_reload_keeps_the_socket_and_the_estimate(tmp_path):
    from compd.config import load_config
    from compd.core.probe import Probe
    from compd.daemon.app import App

    cfg = sim_config(tmp_path, EXTRA.format(), duration_s=600)
    old = App(load_config(cfg))
    old.open()
    new = None
    try:
        old.loop.run(100.0)
        old.loop.adapter.inbox.append(Probe(t_s=old.loop.now_s, axis="z", error_um=float(old.loop.pred_um[0]) + 1))
        old.loop.step(old.loop.now_s + 1.0)
        assert old.loop.adapter.est[0].accepted == 1
        new = App(load_config(cfg))
        new.adopt(old)
        new.open()
        old.close(handing_over_to=new)
        assert new.service.control is old.service.control and (tmp_path / "status.sock").is_socket()
        assert new.service.control.link.axes == ["z"]  # served for the new pipeline
        assert new.loop.adapter.est[0].accepted == 1  # the same model and params: carried over
        answer = control.send_probe(tmp_path / "status.sock", {"op": "probe", "axis": "x", "error_um": 1.0})
        assert not answer["ok"] and "unknown axis" in answer["error"]
    finally:
        (new or old).close()
    assert not (tmp_path / "status.sock").exists()


def test_a_reload_that_changes_the_estimates_terms_starts_it_fresh_and_says_so(tmp_path, caplog):
    """adapt.gain switched on by a reload: the running estimate (offset only) does not fit the new
    one; it starts fresh with an adapt_reset event (it was dropped without a word)."""
    from compd.config import load_config
    from compd.core.probe import Probe
    from compd.daemon.app import App

    cfg = sim_config(tmp_path, EXTRA.format(), duration_s=600)
    old = App(load_config(cfg))
    old.open()
    new = None
    try:
        old.loop.run(100.0)
        old.loop.adapter.inbox.append(Probe(t_s=old.loop.now_s, axis="z", error_um=float(old.loop.pred_um[0]) + 1))
        old.loop.step(old.loop.now_s + 1.0)
        assert old.loop.adapter.est[0].accepted == 1
        cfg.write_text(cfg.read_text(encoding="utf-8").replace("adapt: {}", "adapt: {gain: true}"), encoding="utf-8")
        new = App(load_config(cfg))
        with caplog.at_level(logging.WARNING, logger="compd"):
            new.adopt(old)
        new.open()
        old.close(handing_over_to=new)
        assert new.loop.adapter.est[0].accepted == 0 and new.loop.adapter.est[0].n == 2
        (reset,) = [r for r in caplog.records if getattr(r, "event", None) == "adapt_reset"]
        assert "z: s has 1 terms, the estimate 2" in reset.reason
    finally:
        (new or old).close()


def test_a_state_file_with_a_nan_covariance_is_refused_at_start_and_the_estimate_starts_fresh(tmp_path):
    """What issue 39 saw: a covariance gone NaN, persisted, restored at the next start, and every
    later probe rejected. A real daemon start now refuses it with an event naming it."""
    cfg = sim_config(tmp_path, EXTRA.format(), duration_s=1e6, speedup=0)
    from compd.config import load_config
    from compd.service.state import params_digest

    digest = params_digest(load_config(cfg).model.params)
    axes = {"z": {"s": [2.5], "P": [[math.nan]], "t_probe_s": 10.0, "accepted": 4, "rejected": 1, "probe_age_s": 30.0}}
    (tmp_path / "state.json").write_text(
        json.dumps(
            {
                "format": 1,
                "kind": "xi_spindle",
                "inputs": ["T_xi"],
                "outputs": ["z"],
                "saved_unix_s": time.time(),
                "state": {"t0_c": 19.8, "ref_c": None},
                "adapt": {"params_sha256": digest, "saved_unix_s": time.time(), "axes": axes},
            }
        ),
        encoding="utf-8",
    )
    err, st = run_briefly(tmp_path, cfg)
    assert "event=state_restored" in err  # the model's memory in the same file is sound: taken
    assert "event=adapt_restored" not in err
    (line,) = [ln for ln in err.splitlines() if "event=state_ignored" in ln]
    assert "level=warning" in line and "z: P[0] holds nan" in line, line
    assert st["adapt"]["z"]["accepted"] == 0 and st["adapt"]["z"]["offset_um"] == 0.0
    kept = json.loads((tmp_path / "state.json").read_text(encoding="utf-8"))["adapt"]["axes"]["z"]
    assert kept["accepted"] == 0 and all(math.isfinite(v) for row in kept["P"] for v in row)


def test_a_probe_no_probe_measures_is_refused_at_the_command_line(tmp_path):
    """Issue 39: `--sigma-um 1e200` was accepted and poisoned the estimate. Refused before any daemon
    is asked (none runs here: the old command exited 1, no daemon), exit 2 and one line naming the flag."""
    for args, flag in (
        (["--error-um", "10.3", "--sigma-um", "1e200"], "--sigma-um"),
        (["--error-um", "10.3", "--sigma-um", "1e-9"], "--sigma-um"),
        (["--error-um", "2e4"], "--error-um"),
        (["--error-um", "1", "--position-mm", "1e300"], "--position-mm"),
    ):
        r = compd("probe", "--axis", "z", *args, cwd=tmp_path)
        assert r.returncode == 2 and len(r.stderr.splitlines()) == 1, (args, r.returncode, r.stderr)
        assert r.stderr.startswith(f"compd: {flag}: ") and "Traceback" not in r.stderr, r.stderr


def serving(tmp_path: Path, link: control.ProbeLink) -> control.ControlServer:
    server = control.ControlServer(tmp_path / "status.sock")
    server.open()
    server.serve(link)
    return server


def raw_request(path: Path, data: bytes) -> dict:
    """Send bytes as they are and read the one-line answer; AssertionError when the server closes without one."""
    with socket.socket(socket.AF_UNIX, socket.SOCK_STREAM) as s:
        s.settimeout(WAIT_S)
        s.connect(str(path))
        s.sendall(data)
        got = b""
        while b"\n" not in got:
            chunk = s.recv(65536)
            if not chunk:
                break
            got += chunk
    assert got.endswith(b"\n"), f"the connection closed without an answer: {got!r}"
    return json.loads(got)


def test_the_socket_refuses_a_probe_no_probe_measures(tmp_path, monkeypatch):
    """Another client can send the JSON itself: the daemon's side bounds the numbers too."""
    monkeypatch.setattr(control, "WAIT_S", 0.05)
    link = FakeLink()
    server = serving(tmp_path, link)
    try:
        sock = tmp_path / "status.sock"
        for body, key in (
            ('"error_um": 10.3, "sigma_um": 1e200', "sigma_um"),
            ('"error_um": 1e5', "error_um"),
            ('"error_um": 1.0, "position_mm": 1e300', "position_mm"),
            ('"error_um": 1.0, "sigma_um": NaN', "sigma_um"),
        ):
            answer = raw_request(sock, b'{"op": "probe", "axis": "z", ' + body.encode() + b"}\n")
            assert answer["ok"] is False and answer["error"].startswith(key), (body, answer)
        assert link.sent == []  # none reached the cycle
        assert raw_request(sock, b'{"op": "probe", "axis": "z", "error_um": 10.3, "sigma_um": 2.0}\n')["ok"]
        assert len(link.sent) == 1
    finally:
        server.close()


def test_every_request_is_answered_and_the_server_goes_on_serving(tmp_path, monkeypatch):
    """The control socket's open cases of issue 39: each closed the connection without an answer."""
    monkeypatch.setattr(control, "WAIT_S", 0.05)
    link = FakeLink()
    server = serving(tmp_path, link)
    try:
        sock = tmp_path / "status.sock"
        digits = b"1" * 400
        cases = {
            "a 4000-deep array": b"[" * 4000 + b"]" * 4000 + b"\n",  # longer than a request may be
            "a 2000-deep array": b"[" * 2000 + b"]" * 2000 + b"\n",  # within the length: the parser's recursion
            "a 400-digit error_um": b'{"op": "probe", "axis": "z", "error_um": ' + digits + b"}\n",
            "a 400-digit sigma_um": b'{"op": "probe", "axis": "z", "error_um": 1, "sigma_um": ' + digits + b"}\n",
            "window_s 10**400": b'{"op": "arm_model", "window_s": 1' + b"0" * 400 + b"}\n",
            "not UTF-8": b"\xff\xfe{}\n",
        }
        for what, data in cases.items():
            answer = raw_request(sock, data)
            assert answer["ok"] is False and answer["error"], (what, answer)
            assert len(answer["error"]) < 200, (what, answer)  # a 400-digit number is not echoed whole
        assert "finite" in raw_request(sock, cases["window_s 10**400"])["error"]
        assert link.sent == []
        answer = control.send_probe(sock, {"op": "probe", "axis": "z", "error_um": 1.0})  # still served
        assert answer["ok"] and answer["outcome"] == "queued" and len(link.sent) == 1
        until(lambda: server.served == len(cases) + 2, "every request counted as served")  # counted after its answer
    finally:
        server.close()


class NullLink(FakeLink):
    """A daemon whose verdict holds nulls where numbers were (NaN on the way) and a key of its own."""

    def outcome(self, tag: str) -> dict | None:
        if not self.verdicts or not self.sent or self.sent[-1].source != tag:
            return None
        return {
            "event": "rejected",
            "source": tag,
            "t_s": None,
            "error_um": None,
            "measured_um": None,
            "innovation_um": float("nan"),
            "innovation_sigma_um": None,
            "offset_um": None,
            "reason": "sigma_um must be within [0.001, 1000] um",
            "newer_key": None,
        }


def test_compd_probe_prints_any_answer_nulls_included(tmp_path, monkeypatch):
    """`compd probe` formatted the answer's numbers as numbers: a null (a NaN on the daemon's side,
    or `t_s` of a queued probe) ended in an internal TypeError."""
    monkeypatch.setattr(control, "WAIT_S", 0.05)
    cfg = sim_config(tmp_path, EXTRA.format())
    link = NullLink(verdicts=True)
    server = serving(tmp_path, link)
    try:
        r = compd("probe", "--config", cfg.name, "--axis", "z", "--error-um", "10.3", cwd=tmp_path)
        assert r.returncode == 0 and r.stderr == "", r.stderr
        (line,) = r.stdout.splitlines()
        assert line.startswith("compd: probe z error 10.3 um rejected at t=null s (sigma_um must be within"), line
        assert "innovation null um (sigma null um), offset now null um" in line, line
        assert line.endswith(f"; pid={os.getpid()} measured_um=null newer_key=null"), line
        link.verdicts = False  # the loop takes nothing: queued, t_s null
        r = compd("probe", "--config", cfg.name, "--axis", "z", "--error-um", "10.3", cwd=tmp_path)
        assert r.returncode == 0 and r.stderr == "", r.stderr
        assert (
            r.stdout == f"compd: probe z error 10.3 um queued (the loop has not taken it yet; see the daemon's log);"
            f" t_s=null pid={os.getpid()}\n"
        ), r.stdout
    finally:
        server.close()


def _check(tmp_path: Path, extra: str) -> tuple[int, str, Path]:
    """check-config on the sim spindle with `extra`, in process: its exit code, stderr line, config."""
    from compd.cli import main

    cfg = sim_config(tmp_path, extra)
    err = io.StringIO()
    with contextlib.redirect_stderr(err), contextlib.redirect_stdout(io.StringIO()):
        rc = main(["check-config", str(cfg)])
    return rc, err.getvalue().strip(), cfg


def _line(cfg: Path, text: str) -> int:
    return next(i for i, line in enumerate(cfg.read_text().splitlines(), 1) if text in line)


@pytest.mark.parametrize(
    ("extra", "key", "why"),
    [
        ("adapt: {{socket_path: {long}/p.sock}}", "adapt.socket_path", "bytes long: a Unix socket path is at most 107"),
        ("adapt: {{socket_path: missing/p.sock}}", "adapt.socket_path", "missing of the probe socket"),
        (
            "status: {{path: missing/status.json}}\nadapt: {{}}",
            "status.path",
            "missing of the status file does not exist",
        ),
        ("status: {{path: status.json}}\nadapt: {{}}", "status.path", "status.sock exists and is not a socket"),
    ],
)
def test_check_config_refuses_a_probe_socket_that_cannot_be_bound(tmp_path, extra, key, why):
    """Issue 39 item 7: these passed check-config and then failed `compd run`; now one line naming the key."""
    (tmp_path / "status.sock").write_text("not a socket", encoding="utf-8")
    rc, err, cfg = _check(tmp_path, extra.format(long="x" * 110))
    assert rc == 2 and len(err.splitlines()) == 1, err
    assert f"{cfg}:{_line(cfg, key.split('.')[0] + ':')}: {key}: " in err and why in err, err


def test_check_config_refuses_a_folder_it_cannot_write(tmp_path):
    """A folder compd's user cannot write in (made immutable: root writes anywhere else)."""
    folder = tmp_path / "ro"
    folder.mkdir()
    if subprocess.run(["chattr", "+i", str(folder)], capture_output=True).returncode != 0:
        pytest.skip("chattr +i is not supported on this file system")
    try:
        rc, err, _ = _check(tmp_path, "adapt: {socket_path: ro/p.sock}")
        assert rc == 2 and "adapt.socket_path: the probe socket" in err and "its folder is not writable" in err
        rc, err, _ = _check(tmp_path, "status: {path: ro/status.json}")
        assert rc == 2 and "status.path: the status file" in err and "its folder is not writable" in err
    finally:
        subprocess.run(["chattr", "-i", str(folder)], check=True)


def test_what_check_config_accepts_binds(tmp_path):
    """A socket beside the status file: ok, and the daemon's open binds it (and names status.path when it cannot)."""
    from compd.config import load_config

    rc, err, cfg = _check(tmp_path, "status: {path: status.json}\nadapt: {}")
    assert rc == 0, err
    server = control.ControlServer(control.socket_path(load_config(cfg)), ("status", "path"))
    server.open()
    server.close()
    with pytest.raises(BadInput) as e:
        control.ControlServer(tmp_path / "missing" / "p.sock", ("status", "path")).open()
    assert e.value.path == "status.path" and "does not exist" in e.value.message

"""The service's one thread base: a thread that fails says so once (event, name, reason) and is
seen as ended; a join that times out says so; every service thread is one (names as `top -H` shows)."""

from __future__ import annotations

import logging
import threading

from compd.service.threads import ServiceThread


def test_a_failing_thread_is_logged_once_and_seen_ended(caplog) -> None:  # noqa: ANN001
    caplog.set_level(logging.INFO, logger="compd.service")

    def boom(what: str) -> None:
        raise RuntimeError(what)

    t = ServiceThread("compd-test", boom, "disk on fire")
    t.start()
    assert t.join(30.0)
    assert not t.alive and t.failure == "RuntimeError: disk on fire"
    recs = [r for r in caplog.records if getattr(r, "event", None) == "service_thread_failed"]
    assert len(recs) == 1 and recs[0].service_thread == "compd-test" and recs[0].exc_info is not None


def test_a_join_that_times_out_says_so(caplog) -> None:  # noqa: ANN001
    caplog.set_level(logging.INFO, logger="compd.service")
    release = threading.Event()
    t = ServiceThread("compd-stuck", release.wait)
    t.start()
    try:
        assert not t.join(0.01) and t.alive
        assert [r.service_thread for r in caplog.records if getattr(r, "event", None) == "service_thread_stuck"] == [
            "compd-stuck"
        ]
    finally:
        release.set()
    assert t.join(30.0) and t.failure is None


def test_the_services_threads_are_service_threads(tmp_path) -> None:  # noqa: ANN001
    """The data log's and the state file's writers (the others are built the same way: grep-able)."""
    from pathlib import Path

    from compd.service.logwriter import LogWriter
    from compd.service.state import StateWriter

    lw = LogWriter(Path(tmp_path) / "a.csv", ["t_s", "x"], 0.05)
    sw = StateWriter(Path(tmp_path) / "s.json", "ar1", ["T"], ["z"])
    try:
        names = {t.name for t in threading.enumerate()}
        assert {"compd-log", "compd-state"} <= names
        assert isinstance(lw._thread, ServiceThread) and isinstance(sw._thread, ServiceThread)
    finally:
        lw.close()
        sw.close()

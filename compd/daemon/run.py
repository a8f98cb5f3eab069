"""The daemon behind `compd run`: one pipeline at a time, SIGTERM/SIGINT to stop, SIGHUP to reload its config."""

from __future__ import annotations

import logging
import signal
import sys
from typing import Any

from compd.config import load_config
from compd.core.errors import BadInput
from compd.daemon.app import App
from compd.service.logsetup import setup_logging

log = logging.getLogger("compd")


def reload(app: App, config_path: str, remaining: float | None, observe: bool | None) -> App:
    """One config reload; returns the App that runs on: the new one, or `app` unchanged.

    The new pipeline is built and opened (everything that can fail: plant clock, metrics
    bind, state, log, sources, sink) before the running one is closed; if any of that
    fails the new one is undone and the old one goes on compensating, without a step.
    """
    try:
        new = App(load_config(config_path), duration_s=remaining, observe=observe)
    except BadInput as e:
        log.error(
            "reload rejected, still running the old config: %s",
            e,
            extra={"event": "reload_rejected", "config": config_path, "reason": str(e)},
        )
        print(f"compd: reload rejected, still running the old config: {e}", file=sys.stderr)
        return app
    except Exception as e:  # building the pipeline failed in a way no check foresaw
        reason = f"{type(e).__name__}: {e}"
        log.error(
            "reload failed, still running the old config: %s",
            reason,
            extra={"event": "reload_failed", "config": config_path, "reason": reason},
        )
        print(f"compd: reload failed, still running the old config: {reason}", file=sys.stderr)
        return app
    log.info("reloading %s", config_path, extra={"event": "reloading", "config": config_path})
    new.adopt(app)
    try:
        new.open()  # undoes itself if a step fails; `app` is untouched then
    except Exception as e:
        reason = str(e) if isinstance(e, BadInput) else f"{type(e).__name__}: {e}"
        log.error(
            "reload failed, still running the old config: %s",
            reason,
            extra={"event": "reload_failed", "config": config_path, "reason": reason},
        )
        print(f"compd: reload failed, still running the old config: {reason}", file=sys.stderr)
        return app
    try:
        app.close(handing_over_to=new)
    except Exception as e:  # the old pipeline's release failed: the new one runs regardless
        log.warning(
            "closing the old pipeline after a reload: %s: %s",
            type(e).__name__,
            e,
            extra={"event": "reload_close_error", "reason": str(e)},
        )
    log.info("reloaded %s", config_path, extra={"event": "reloaded", "config": config_path})
    print(f"compd: reloaded {config_path}", file=sys.stderr)
    return new


def run_with_reload(
    config_path: str, duration_s: float | None, observe: bool = False, log_level: str | None = None
) -> dict[str, Any] | None:
    """Run the loop until SIGTERM/SIGINT or the duration; SIGHUP reloads the config.

    A reload validates the new config, builds and opens the new pipeline before the
    running one is closed; if any of that fails the daemon logs why (`reload_rejected`
    or `reload_failed`) and goes on with the old pipeline: a reload never stops compd.
    Reloads are serialised and the last request wins: a SIGHUP that arrives during a
    reload triggers one more reload of the then-current file after it. Returns the
    summary of the last pipeline.

    The signal handlers are installed first, before the config is read and the pipeline
    built (a second or more): a SIGHUP then is a reload served once the loop runs, not the
    default action that ends the process without a word; a SIGTERM or SIGINT before anything
    was opened ends it with nothing to make safe (None), after that with the safe output.
    Python runs no handler before it runs this module: a signal in the interpreter's own
    start (tens of ms) still takes its default action. The previous handlers are back on return.
    """
    # set only by the signal handlers (which run on this thread, between statements)
    requests = {"stop": False, "reload": 0}
    current: list[App | None] = [None]  # the App that runs, once there is one

    def on_stop(signum: int, frame: object) -> None:
        requests["stop"] = True
        if current[0] is not None:
            current[0].loop.stop()

    def on_hup(signum: int, frame: object) -> None:
        requests["reload"] += 1
        if current[0] is not None:
            current[0].loop.stop()

    handlers = {signal.SIGTERM: on_stop, signal.SIGINT: on_stop, signal.SIGHUP: on_hup}
    previous = {signum: signal.signal(signum, handler) for signum, handler in handlers.items()}
    try:
        return _run(config_path, duration_s, observe, log_level, requests, current)
    finally:
        for signum, handler in previous.items():
            signal.signal(signum, handler)


def _run(
    config_path: str,
    duration_s: float | None,
    observe: bool,
    log_level: str | None,
    requests: dict[str, Any],
    current: list[App | None],
) -> dict[str, Any] | None:
    """`run_with_reload` once its handlers are in place: the config read, the App built and run."""
    cfg = load_config(config_path)
    setup_logging(log_level or cfg.top.logging.level)
    observe_flag = True if observe else None
    app = None if requests["stop"] else App(cfg, duration_s=duration_s, observe=observe_flag)
    if app is None or requests["stop"]:  # asked to stop before anything was opened: nothing to make safe
        log.info(
            "stopped before the loop started: nothing was opened",
            extra={"event": "stopped_early", "config": config_path},
        )
        return None
    current[0] = app
    remaining = app.duration_s
    app.open()
    try:
        while True:
            app.loop.resume()  # a request from here on stops the run below at once
            app.service.resume()  # after a reload that was refused: the status says running again
            if not requests["stop"] and not requests["reload"]:
                t0 = app.clock.now()
                app.loop.run(remaining)
                if remaining is not None:
                    remaining -= app.clock.now() - t0
            if requests["stop"] or not requests["reload"] or (remaining is not None and remaining <= 0):
                break
            requests["reload"] = 0  # served from here: a SIGHUP during this reload asks for one more
            app.service.reloading()  # the loop pauses: the status says reloading, not a dead cycle
            app = current[0] = reload(app, config_path, remaining, observe_flag)
    finally:
        app.close()
    return app.summary_dict()

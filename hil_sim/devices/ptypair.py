"""A linked pair of pseudo-terminals made by socat: the device opens one end, compd the other."""

from __future__ import annotations

import os
import shutil
import subprocess
import time
from pathlib import Path


class PtyPair:
    """`socat pty,raw,echo=0,link=A pty,raw,echo=0,link=B`; `a` and `b` are the link paths."""

    def __init__(self, a: str | Path, b: str | Path) -> None:
        self.a = str(a)
        self.b = str(b)
        self.proc: subprocess.Popen[bytes] | None = None

    def start(self, timeout_s: float = 5.0) -> PtyPair:
        exe = shutil.which("socat")
        if exe is None:
            raise RuntimeError("socat is not installed (make sysdeps installs it)")
        for p in (self.a, self.b):
            if os.path.lexists(p):
                os.unlink(p)
        self.proc = subprocess.Popen(
            [exe, f"pty,raw,echo=0,link={self.a}", f"pty,raw,echo=0,link={self.b}"],
            stdin=subprocess.DEVNULL,
            stdout=subprocess.DEVNULL,
            stderr=subprocess.DEVNULL,
        )
        deadline = time.monotonic() + timeout_s
        while not (os.path.exists(self.a) and os.path.exists(self.b)):
            if self.proc.poll() is not None or time.monotonic() > deadline:
                self.stop()
                raise RuntimeError("socat did not create the pseudo-terminal pair")
            time.sleep(0.01)
        return self

    def stop(self) -> None:
        if self.proc is not None:
            self.proc.terminate()
            try:
                self.proc.wait(5)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait(5)
            self.proc = None

    def __enter__(self) -> PtyPair:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.stop()

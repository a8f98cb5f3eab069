"""Helpers for source tests: run a source on its own against a wall clock."""

from __future__ import annotations

import time

from compd.core.clock import WallClock
from compd.core.frame import Frame, Quality


class Harness:
    """A frame, a wall clock and one source, opened and polling."""

    def __init__(self, source) -> None:
        self.source = source
        self.clock = WallClock()
        self.frame = Frame(source.signal_names())
        source.bind(self.frame)

    def __enter__(self) -> Harness:
        self.source.open(self.clock.now())
        self.source.start_polling(self.clock)  # no-op for a source read in the cycle
        return self

    def __exit__(self, *exc: object) -> None:
        self.source.close()

    def sample(self, polls: int = 2, timeout_s: float = 10.0) -> dict[str, tuple[float, str]]:
        """Wait for `polls` more completed polls, then read: name → (value, quality name)."""
        src = self.source
        if hasattr(src, "polls"):
            want = src.polls + polls
            deadline = time.monotonic() + timeout_s
            while src.polls < want:
                if time.monotonic() > deadline:
                    raise TimeoutError("source did not poll")
                time.sleep(0.005)
        src.read(self.frame, self.clock.now())
        return {
            n: (float(self.frame.values[i]), Quality(int(self.frame.quality[i])).name)
            for i, n in enumerate(self.frame.names)
        }

    def sample_good(self, max_polls: int = 50) -> dict[str, tuple[float, str]]:
        """Sample until every signal is GOOD (a device recovering from a fault), at most
        `max_polls` polls: on a busy machine a reply may still come late a poll or two after
        the fault is cleared. Returns the last sample, GOOD or not, for the caller to assert."""
        s = self.sample(polls=1)
        for _ in range(max_polls):
            if all(q == "GOOD" for _, q in s.values()):
                break
            s = self.sample(polls=1)
        return s

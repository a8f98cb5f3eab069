"""Shared fixtures. Every test must leave no thread, child process or socket behind."""

from __future__ import annotations

import ast
import functools
import os
import threading
import time
from collections import OrderedDict
from pathlib import Path
from typing import Any

import pytest

ROOT = Path(__file__).resolve().parent.parent


def _sockets() -> set[str]:
    out = set()
    for fd in os.listdir("/proc/self/fd"):
        try:
            target = os.readlink(f"/proc/self/fd/{fd}")
        except OSError:
            continue
        if target.startswith("socket:"):
            out.add(target)
    return out


def _children() -> set[int]:
    me = os.getpid()
    kids = set()
    for pid in os.listdir("/proc"):
        if not pid.isdigit():
            continue
        try:
            with open(f"/proc/{pid}/stat") as fh:
                fields = fh.read().rsplit(")", 1)[1].split()
        except OSError:
            continue
        if int(fields[1]) == me and fields[0] != "Z":
            kids.add(int(pid))
    return kids


@functools.cache
def _test_modules() -> dict[str, ast.Module]:
    """Every test module, parsed once: {path from the checkout: its syntax tree}."""
    return {
        file.relative_to(ROOT).as_posix(): ast.parse(file.read_text(encoding="utf-8"))
        for file in (ROOT / "tests").rglob("test_*.py")
    }


@functools.cache
def _modules_sharing_a_fixture() -> frozenset[str]:
    """The test modules (paths from the checkout) that define a fixture made once for many tests:
    `@pytest.fixture(scope=...)` with any scope but function."""
    out = set()
    for path, tree in _test_modules().items():
        for node in ast.walk(tree):
            if not (isinstance(node, ast.Call) and ast.unparse(node.func) in ("pytest.fixture", "fixture")):
                continue
            scope = next((k.value for k in node.keywords if k.arg == "scope"), None)
            if scope is not None and not (isinstance(scope, ast.Constant) and scope.value == "function"):
                out.add(path)
    return frozenset(out)


@functools.cache
def _slow() -> tuple[frozenset[str], frozenset[str]]:
    """(the test modules marked slow as a whole, `pytestmark`; the tests marked slow one by one, as
    "path::function"), paths from the checkout: `@pytest.mark.slow`, the longer scenario tests."""
    modules, functions = set(), set()
    for path, tree in _test_modules().items():
        for node in tree.body:
            if isinstance(node, ast.Assign) and any(ast.unparse(t) == "pytestmark" for t in node.targets):
                if "pytest.mark.slow" in ast.unparse(node.value):
                    modules.add(path)
            elif isinstance(node, ast.FunctionDef) and any(
                ast.unparse(d).startswith("pytest.mark.slow") for d in node.decorator_list
            ):
                functions.add(f"{path}::{node.name}")
    return frozenset(modules), frozenset(functions)


def is_slow(nodeid: str) -> bool:
    """Whether a test is marked slow (its function, or its module's `pytestmark`)."""
    modules, functions = _slow()
    path, _, rest = nodeid.partition("::")
    return path in modules or f"{path}::{rest.split('[', 1)[0]}" in functions


class CostliestFirst(OrderedDict):
    """xdist's queue of work units (scope: {node id: done}), which it takes from the front: the front is
    the unit with the most tests marked slow, then the most tests, then the first queued."""

    def __init__(self) -> None:
        super().__init__()
        self._costs: dict[str, tuple[int, int]] = {}  # counted once, as a unit is queued

    def __setitem__(self, scope: str, unit: dict[str, bool]) -> None:
        super().__setitem__(scope, unit)
        self._costs[scope] = (sum(map(is_slow, unit)), len(unit))

    def popitem(self, last: bool = True) -> tuple[str, dict[str, bool]]:
        if last or not self:
            return super().popitem(last=last)
        scope = max(self, key=self._costs.__getitem__)
        return scope, self.pop(scope)


def xdist_scope(nodeid: str) -> str:
    """The unit of work a test belongs to under `make test`'s `-n N --dist loadgroup`: every test of
    tests/linuxcnc together (one LinuxCNC per machine: a second worker's Sim would only wait on
    tests/linuxcnc/sim.py's lock), the tests of a module with a module-scoped (or wider) fixture together
    (the fixture is made once, not once per worker), any other test alone."""
    path = nodeid.split("::", 1)[0]
    if path.startswith("tests/linuxcnc/"):
        return "linuxcnc"
    return path if path in _modules_sharing_a_fixture() else nodeid


@pytest.hookimpl(optionalhook=True)
def pytest_xdist_make_scheduler(config: pytest.Config, log: Any) -> Any:
    """`--dist loadgroup` grouped by `xdist_scope` as well as by xdist_group marks: pytest-xdist 3.8
    reads the marks through the node id, which pytest 9.2 no longer lets it change (pytest-xdist
    issue 1386), and a mark on every test of a module would be easy to forget. Groups of many tests
    are handed out costliest first: the most tests marked slow, then the most tests, so that the
    longest do not start last (on 8943cb8 the demo's 100 s was among the last tests started)."""
    if config.getvalue("dist") != "loadgroup":
        return None
    from xdist.scheduler import LoadGroupScheduling

    class Scheduling(LoadGroupScheduling):
        def __init__(self, config: pytest.Config, log: Any) -> None:
            super().__init__(config, log)
            self.workqueue = CostliestFirst()

        def _split_scope(self, nodeid: str) -> str:
            marked = super()._split_scope(nodeid)
            return marked if marked != nodeid else xdist_scope(nodeid)

    return Scheduling(config, log)


@pytest.fixture(autouse=True)
def no_leaks():
    """Fail a test that leaves a thread, a child process or a socket open."""
    threads = set(threading.enumerate())
    socks = _sockets()
    kids = _children()
    yield
    deadline = time.monotonic() + 3.0
    while True:
        extra_threads = [t for t in threading.enumerate() if t not in threads and t.is_alive()]
        extra_socks = _sockets() - socks
        extra_kids = _children() - kids
        if not (extra_threads or extra_socks or extra_kids) or time.monotonic() > deadline:
            break
        time.sleep(0.05)
    problems = []
    if extra_threads:
        problems.append(f"threads left running: {[t.name for t in extra_threads]}")
    if extra_socks:
        problems.append(f"sockets left open: {len(extra_socks)}")
    if extra_kids:
        problems.append(f"child processes left running: {sorted(extra_kids)}")
    if problems:
        pytest.fail("; ".join(problems))


@pytest.fixture
def root() -> Path:
    return ROOT

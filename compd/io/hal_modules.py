"""LinuxCNC's Python modules `hal` and `linuxcnc`, loaded from Debian's files into compd's Python.

LinuxCNC ships its Python modules in the system's dist-packages (Debian's linuxcnc-uspace:
/usr/lib/python3/dist-packages/hal.py, _hal.cpython-311-*.so, linuxcnc.cpython-311-*.so),
beside Debian's own numpy and the rest, which are not compd's venv's. So that folder is
never put on sys.path: `load()` loads just the three files by their paths (the `_hal`
extension module, `hal.py` over it, the `linuxcnc` extension module), registering each in
sys.modules under its own name (hal.py's `import _hal` finds it there), once per process.
The folder is $COMPD_LINUXCNC_PYTHON when set.

`_hal`'s initialisation sets SIGTERM to raise KeyboardInterrupt (`signal.signal(SIGTERM,
default_int_handler)`): in compd, which installs its handlers before it opens its sinks, that
would turn a stop request into an exception at any statement of the loop, and from a thread
other than the main one the call fails and prints a traceback. So `_hal` initialises with
`signal.signal` standing in for a no-op: the process keeps its handlers. LinuxCNC's shutdown
(`halcmd unload all`) SIGTERMs the process of every userspace component: compd then stops as
on any SIGTERM; a process that kept the default action ends.

A file that is missing or does not load (built for another Python, a missing library) is a
`BadInput` with one line saying which and what to do; nothing of a failed attempt is kept
(its sys.modules entries are removed), and only a success is cached, per folder.
"""

from __future__ import annotations

import contextlib
import importlib.machinery
import importlib.util
import os
import signal
import sys
import threading
from collections.abc import Iterator
from importlib.abc import Loader
from pathlib import Path
from types import ModuleType
from typing import Any

from compd.core.errors import BadInput

ENV = "COMPD_LINUXCNC_PYTHON"
DEFAULT_FOLDER = "/usr/lib/python3/dist-packages"
_INSTALL = "install Debian's linuxcnc-uspace (make sysdeps)"

_lock = threading.Lock()
_loaded: dict[str, tuple[ModuleType, ModuleType]] = {}  # folder -> (hal, linuxcnc): successes only


def folder() -> Path:
    """Where LinuxCNC's Python modules are looked for: $COMPD_LINUXCNC_PYTHON, else Debian's dist-packages."""
    return Path(os.environ.get(ENV) or DEFAULT_FOLDER)


def load() -> tuple[ModuleType, ModuleType]:
    """LinuxCNC's `hal` and `linuxcnc` modules; `BadInput` (one line) when they cannot be loaded."""
    where = folder()
    key = str(where)
    with _lock:
        if key in _loaded:
            return _loaded[key]
        # every file found before any is loaded; hal.py, the name users know, is asked for first
        hal_py = _source(where, "hal")
        hal_so = _extension(where, "_hal")
        linuxcnc_so = _extension(where, "linuxcnc")
        before = {name: sys.modules.get(name) for name in ("_hal", "hal", "linuxcnc")}
        try:
            with _handlers_kept():
                _exec("_hal", hal_so, importlib.machinery.ExtensionFileLoader("_hal", str(hal_so)))
            hal = _exec("hal", hal_py, importlib.machinery.SourceFileLoader("hal", str(hal_py)))
            linuxcnc = _exec(
                "linuxcnc", linuxcnc_so, importlib.machinery.ExtensionFileLoader("linuxcnc", str(linuxcnc_so))
            )
        except BaseException:
            for name, module in before.items():  # a later attempt finds no half-loaded module
                if module is None:
                    sys.modules.pop(name, None)
                else:
                    sys.modules[name] = module
            raise
        _loaded[key] = (hal, linuxcnc)
        return hal, linuxcnc


def available() -> str | None:
    """None when `load()` works, else its one-line reason (for tests and check-config)."""
    try:
        load()
    except BadInput as exc:
        return str(exc)
    return None


def _hint() -> str:
    if os.environ.get(ENV):
        return f"{_INSTALL}, or set {ENV} to the folder that holds LinuxCNC's hal.py"
    return _INSTALL


def _source(where: Path, name: str) -> Path:
    path = where / f"{name}.py"
    if not path.is_file():
        raise BadInput(f"LinuxCNC's Python module {name} is not installed ({path}): {_hint()}")
    return path


def _extension(where: Path, name: str) -> Path:
    """The file of extension module `name` in `where` built for this Python (its EXTENSION_SUFFIXES)."""
    suffixes = importlib.machinery.EXTENSION_SUFFIXES
    for suffix in suffixes:
        path = where / f"{name}{suffix}"
        if path.is_file():
            return path
    others = sorted(p.name for p in where.glob(f"{name}.*.so")) if where.is_dir() else []
    if others:
        version = f"{sys.version_info.major}.{sys.version_info.minor}"
        raise BadInput(
            f"LinuxCNC's Python module {name} in {where} is built for another Python ({', '.join(others)}), "
            f"compd runs Python {version}: run compd with the Python that LinuxCNC was built for"
        )
    raise BadInput(f"LinuxCNC's Python module {name} is not installed ({where / (name + suffixes[0])}): {_hint()}")


def _exec(name: str, path: Path, loader: Loader) -> ModuleType:
    """Load `path` as module `name`, registered in sys.modules before it runs (as an import does)."""
    present = sys.modules.get(name)
    if present is not None and _same(getattr(present, "__file__", None), path):
        return present  # already imported from this very file (e.g. under Debian's own Python)
    try:
        spec = importlib.util.spec_from_file_location(name, path, loader=loader)
        if spec is None:
            raise ImportError("not a module file")
        module = importlib.util.module_from_spec(spec)
        sys.modules[name] = module
        loader.exec_module(module)
    except Exception as exc:
        detail = " ".join(f"{type(exc).__name__}: {exc}".split())
        raise BadInput(f"LinuxCNC's Python module {name} does not load ({path}: {detail}): {_hint()}") from None
    return module


@contextlib.contextmanager
def _handlers_kept() -> Iterator[None]:
    """`signal.signal` a no-op for the block (it returns the handler in place): `_hal`'s init sets none."""
    real = signal.signal

    def keep(signalnum: int, handler: Any) -> Any:
        return signal.getsignal(signalnum)

    signal.signal = keep
    try:
        yield
    finally:
        signal.signal = real


def _same(a: str | None, b: Path) -> bool:
    try:
        return a is not None and os.path.samefile(a, b)
    except OSError:
        return False

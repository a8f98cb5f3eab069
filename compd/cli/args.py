"""What every command shares: argument types, output checks, the parser with compd's error form, the command table."""

from __future__ import annotations

import argparse
import contextlib
import math
import os
import typing
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

from compd.core.errors import BadInput

Handler = Callable[[argparse.Namespace], int]
COMMANDS: dict[str, Handler] = {}  # name → what it does
ARGUMENTS: dict[str, Callable[[Any], None]] = {}  # name → what adds its parser and arguments


def command(name: str, arguments: Callable[[Any], None]) -> Callable[[Handler], Handler]:
    """Register a command: its handler, and `arguments(sub)`, which adds its parser to the
    subparsers `sub` (written beside the handler)."""

    def deco(fn: Handler) -> Handler:
        COMMANDS[name] = fn
        ARGUMENTS[name] = arguments
        return fn

    return deco


def _number(text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"not a number: {text!r}") from None
    if not math.isfinite(value):
        raise argparse.ArgumentTypeError(f"must be a finite number, got {text!r}")
    return value


def finite(text: str) -> float:
    """argparse type: a finite number (NaN and infinities are malformed here)."""
    return _number(text)


def positive(text: str) -> float:
    """argparse type: a finite number > 0 (a duration, a period, an LSB)."""
    value = _number(text)
    if value <= 0:
        raise argparse.ArgumentTypeError(f"must be > 0, got {text!r}")
    return value


def count(text: str) -> int:
    """argparse type: a whole number ≥ 1 (how many of something)."""
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"not a whole number: {text!r}") from None
    if value < 1:
        raise argparse.ArgumentTypeError(f"must be ≥ 1, got {text!r}")
    return value


def non_negative(text: str) -> float:
    """argparse type: a finite number ≥ 0."""
    value = _number(text)
    if value < 0:
        raise argparse.ArgumentTypeError(f"must be ≥ 0, got {text!r}")
    return value


def check_output(path: str | None, flag: str, *, folder: bool = False) -> None:
    """BadInput unless `path` can be written — checked before the work starts, so a long
    fit or run does not end in an error. A file that did not exist is not left behind."""
    if path is None:
        return
    p = Path(path)
    if folder:
        if p.exists() and not p.is_dir():
            raise BadInput("exists and is not a folder", file=path, path=flag)
        try:
            p.mkdir(parents=True, exist_ok=True)
        except OSError as e:
            raise BadInput(f"cannot create the folder: {e.strerror or e}", file=path, path=flag) from None
        return
    if p.is_dir():
        raise BadInput("is a folder, not a file", file=path, path=flag)
    existed = p.exists()
    try:
        with open(p, "a", encoding="utf-8"):
            pass
        if not existed:
            p.unlink()
    except OSError as e:
        raise BadInput(f"cannot write: {e.strerror or e}", file=path, path=flag) from None


def check_plot(path: str | None, flag: str = "--plot") -> None:
    """check_output, and a file type matplotlib can write (a figure is drawn after the work)."""
    if path is None:
        return
    suffix = Path(path).suffix.lower().lstrip(".")
    if suffix:
        try:
            from matplotlib.backend_bases import FigureCanvasBase
        except ImportError:
            raise BadInput(f"{flag} needs matplotlib: pip install 'compd[plot]'", path=flag) from None
        known = FigureCanvasBase.get_supported_filetypes()
        if suffix not in known:
            raise BadInput(f"cannot plot to a .{suffix} file (known: {', '.join(sorted(known))})", file=path, path=flag)
    check_output(path, flag)


@contextlib.contextmanager
def writing(path: str | os.PathLike[str], flag: str) -> Iterator[None]:
    """An OSError while writing `path` (disk full, the folder gone since the check) is bad input."""
    try:
        yield
    except OSError as e:
        raise BadInput(f"cannot write: {e.strerror or e}", file=str(path), path=flag) from None


class Parser(argparse.ArgumentParser):
    """argparse with compd's error form: one line on stderr, exit 2 (`--help` shows the usage).
    The description and the epilog (an example) are printed as written; `epilog_extra`, when
    set, adds text computed only when the help is shown (the fit options per kind)."""

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        kwargs.setdefault("formatter_class", argparse.RawDescriptionHelpFormatter)
        super().__init__(*args, **kwargs)
        self.epilog_extra: Callable[[], str] | None = None

    def format_help(self) -> str:
        if self.epilog_extra is None:
            return super().format_help()
        saved = self.epilog
        self.epilog = f"{self.epilog_extra()}\n\n{saved or ''}".rstrip()
        try:
            return super().format_help()
        finally:
            self.epilog = saved

    def error(self, message: str) -> typing.NoReturn:
        one_line = " ".join(message.split())
        self.exit(2, f"{self.prog}: {one_line}\n")

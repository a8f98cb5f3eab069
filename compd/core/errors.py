"""Error types shared by every stage: bad input (exit 2) versus everything else."""

from __future__ import annotations

from collections.abc import Sequence


def format_path(path: Sequence[str | int]) -> str:
    """A key path as users write it: `sources[0].registers.start`."""
    out = ""
    for part in path:
        if isinstance(part, int):
            out += f"[{part}]"
        else:
            out += ("." if out else "") + str(part)
    return out


class BadInput(Exception):
    """Bad input from the user (config, file, argument): the CLI exits 2.

    The message is one line naming the file, the line where known and the key path
    or column.
    """

    def __init__(
        self,
        message: str,
        *,
        file: str | None = None,
        line: int | None = None,
        path: Sequence[str | int] | str | None = None,
    ) -> None:
        self.message = message
        self.file = file
        self.line = line
        # the key path as given (a tuple), so a caller that knows where the section sits
        # can place it in its file (Document.error); a string path is one key
        self.keys: tuple[str | int, ...] = () if path is None else (path,) if isinstance(path, str) else tuple(path)
        self.path = path if isinstance(path, str) or path is None else format_path(path)
        super().__init__(str(self))

    def __reduce__(self) -> tuple[object, ...]:
        # whole across a process boundary (an I/O worker's child raises it at start-up)
        return (_rebuilt, (type(self), self.message, self.file, self.line, self.keys or None))

    def __str__(self) -> str:
        where = ""
        if self.file:
            where = self.file
            if self.line is not None:
                where += f":{self.line}"
            where += ": "
        key = f"{self.path}: " if self.path else ""
        return f"{where}{key}{self.message}".replace("\n", " ")


def _rebuilt(
    cls: type[BadInput], message: str, file: str | None, line: int | None, keys: tuple[str | int, ...] | None
) -> BadInput:
    return cls(message, file=file, line=line, path=keys)


class ConfigError(BadInput):
    """A config file that does not validate."""

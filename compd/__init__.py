"""compd: real-time thermal-error compensation daemon for CNC machine tools."""

__version__ = "0.1.0"


_version: str | None = None


def version() -> str:
    """compd's version: the installed package's metadata, else the source tree's `__version__`
    (read once: the metadata is a file parsed on every read, and the status asks every second)."""
    global _version
    if _version is None:
        from importlib.metadata import PackageNotFoundError
        from importlib.metadata import version as dist_version

        try:
            _version = dist_version("compd")
        except PackageNotFoundError:
            _version = __version__
    return _version

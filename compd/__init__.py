"""compd: real-time thermal-error compensation daemon for CNC machine tools."""

__version__ = "0.1.0"


def version() -> str:
    """compd's version: the installed package's metadata, else the source tree's `__version__`."""
    from importlib.metadata import PackageNotFoundError
    from importlib.metadata import version as dist_version

    try:
        return dist_version("compd")
    except PackageNotFoundError:
        return __version__

"""compd: real-time thermal-error compensation daemon for CNC machine tools."""

__version__ = "0.1.0"

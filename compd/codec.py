"""The contract's name of the word's codec: `compd.codec.encode` and `compd.codec.decode` are compd.cycle.codec's (docs/formats.md)."""

from compd.cycle.codec import decode, encode

__all__ = ["decode", "encode"]

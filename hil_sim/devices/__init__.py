"""Emulated devices that compd talks to (cards, transmitters, CNC controllers)."""

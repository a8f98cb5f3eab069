"""Commissioning off the machine: fit, replay, output-test, plots, reports, and the docs generated from the code."""

"""The ground floor every process stands on: errors, the frame, clocks, the kind registry, the strict config base
and its sections, the probe record and scoring; it imports nothing of compd above it."""

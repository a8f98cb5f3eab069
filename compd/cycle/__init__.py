"""The cycle's process: the pipeline's stages, the loop and its clock, and the status record it hands the service.

The stages: frame, guard, codec, adapt, inhibit.
"""

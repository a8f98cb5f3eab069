"""The cycle's process: the pipeline's stages (frame, guard, codec, adapt, inhibit), the loop and its clock, and the status record it hands the service."""

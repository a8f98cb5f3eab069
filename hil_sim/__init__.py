"""hil_sim: the thermal plants of the papers and the devices compd talks to."""

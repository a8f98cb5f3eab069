"""The closed-loop test rig: a hil_sim plant over the real protocols, compd running against it, fits for acceptance.

It sits above both packages: hil_sim simulates the machine and its devices, compd
compensates it, and the rig wires one to the other (`closedloop`: a machine's unseen
day, scored on the plant's residual log; `bench`: `compd bench`, the 2 ms cycle against
served devices, reached by compd's CLI through the `compd.commands` entry point).
"""

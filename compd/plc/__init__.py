"""The software PLC: the FANUC PMC, the Siemens NC's compensation data and the PCI-1756 card as virtual devices.

A sink without a `host` writes to one of these in this process, on the loop's time
(replay, the demo, tests), through `VirtualLink`: the same interface as the Modbus
link it uses for the real device, so a sink has one code path for both. The same
devices can be served over Modbus TCP by a simulator, which then stands in for the
machine.
"""

"""The devices compd talks to, over their real protocols: transmitters, compd's software PLC CNCs, the live plant."""

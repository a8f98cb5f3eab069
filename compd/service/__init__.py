"""The service's process: status file and `compd status`, metrics, probe socket, systemd notify.

Also the model state and the event log lines.
"""

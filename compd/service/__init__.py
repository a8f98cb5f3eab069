"""The service's process: status file and `compd status`, metrics, probe socket, systemd notify, model state, event log lines."""

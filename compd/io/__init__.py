"""Device I/O beside the cycle: one worker thread per device (`worker`), the mailboxes it shares with
the cycle (`mailbox`) and the one Modbus client (`modbus_client`)."""

"""telesurg services: each subpackage is one process (master_capture, mapping, slave_control, watchdog, mirror)."""

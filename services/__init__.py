"""telesurg services: one subpackage per process (the table of them: shared/service_table.py)."""

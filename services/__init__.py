"""telesurg services: one subpackage per process."""

"""``python -m telesurg.services.certs``: the same as ``telesurg certs``."""

from telesurg.services.certs import main

if __name__ == "__main__":
    raise SystemExit(main())

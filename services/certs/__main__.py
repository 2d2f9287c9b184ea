"""``python -m services.certs``: the same as ``telesurg certs``."""

from services.certs import main

if __name__ == "__main__":
    raise SystemExit(main())

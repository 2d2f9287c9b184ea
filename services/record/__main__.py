"""``python -m telesurg.services.record``: the same as ``telesurg record``."""

from telesurg.services.record import main

if __name__ == "__main__":
    raise SystemExit(main())

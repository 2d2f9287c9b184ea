"""``python -m telesurg.services.device``: the same as ``telesurg device``."""

from telesurg.services.device import main

if __name__ == "__main__":
    raise SystemExit(main())

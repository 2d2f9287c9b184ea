"""``python -m services.device``: the same as ``telesurg device``."""

from services.device import main

if __name__ == "__main__":
    raise SystemExit(main())

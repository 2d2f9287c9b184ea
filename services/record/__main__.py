"""``python -m services.record``: the same as ``telesurg record``."""

from services.record import main

if __name__ == "__main__":
    raise SystemExit(main())

"""``python -m telesurg.tools.emulate``: the same as ``telesurg device``."""

from telesurg.tools.emulate import main

if __name__ == "__main__":
    raise SystemExit(main())

"""Master → slave arm pairs, as a site's configuration states them (``pairs = ["m1:arm1"]``).

The mapping, the watchdog and the launcher's demo read the same strings, so they parse them here.

Example::

    >>> parse_pair("m1:arm1")
    ('m1', 'arm1')
"""

from __future__ import annotations

from telesurg.shared.errors import ConfigError
from telesurg.shared.keys import check_id


def parse_pair(pair: str) -> tuple[str, str]:
    """``"m1:arm1"`` → ``("m1", "arm1")``; a string without ``:`` or with a bad arm id raises
    :class:`~telesurg.shared.errors.ConfigError`."""
    master, sep, slave = pair.partition(":")
    if not sep:
        raise ConfigError(f"pair {pair!r} must look like master_arm:slave_arm")
    return check_id("arm", master), check_id("arm", slave)

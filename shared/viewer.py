"""The address of the rerun web viewer the mirror serves (``serve = true``).

The mirror builds it from the server it started; the launcher's demo prints it from the ports it
gave the mirror. Pure string work (no rerun import), so the launcher needs no mirror module.

Example::

    >>> viewer_url("rerun+http://127.0.0.1:9876/proxy", 9090)
    'http://localhost:9090/?url=rerun%2Bhttp://127.0.0.1:9876/proxy'
"""

from __future__ import annotations

import urllib.parse


def viewer_url(grpc_uri: str, web_port: int) -> str:
    """Web viewer URL that opens ``grpc_uri``, the form rerun itself prints."""
    return f"http://localhost:{web_port}/?url={urllib.parse.quote(grpc_uri, safe=':/')}"

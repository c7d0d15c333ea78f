"""The server's web pages: where they are, and ``python -m dinerdash watch``.

A server started with ``--http-port P`` serves its live sessions at ``http://HOST:P/`` and any
environment playing at ``http://HOST:P/watch/{session_id}?env=K`` (``https://`` when it serves
TLS: the pages use the certificate of gRPC, so a client connected with TLS gets HTTPS URLs). The
server tells where in ``ServerInfo`` (``http_port``, ``http_host``), so the client needs no second
address: the pages' host is the one they listen on, or, when that is a wildcard (``--http-host
0.0.0.0``), the host the client reached the server by. A session ID is a capability: its watch
URL lets whoever holds it watch (the page also asks for a token when the server has tokens).

::

    python -m dinerdash watch --address 127.0.0.1:50051   # prints the URL, opens a browser
    env.unwrapped.watch_url()                              # one environment's page

(the command itself is :mod:`dinerdash.cli`'s, over :func:`pages_url`, :func:`watch_url` and
:func:`open_browser`).
"""

from __future__ import annotations

import os
import sys
import webbrowser

from .connection import Connection, join_host_port, split_host_port
from .errors import FailedPrecondition

__all__ = ["open_browser", "pages_url", "watch_url"]

_WILDCARDS = ("", "0.0.0.0", "::", "[::]")


def pages_url(conn: Connection) -> str:
    """The URL of the sessions page of the server behind ``conn``.

    Raises:
        FailedPrecondition: the server serves no pages (it was started without ``--http-port``).
    """
    info = conn.server_info()
    if not info.http_port:
        raise FailedPrecondition(
            "the server serves no web pages: start it with --http-port PORT (e.g. 8080)",
            address=conn.address,
        )
    host = info.http_host
    if host in _WILDCARDS:
        host = split_host_port(conn.address)[0]
    # A server with a certificate serves its pages over TLS too, with the same certificate.
    scheme = "https" if getattr(conn, "tls", False) else "http"
    return f"{scheme}://{join_host_port(host, info.http_port)}/"


def watch_url(conn: Connection, session_id: str, env: int = 0) -> str:
    """The URL of the page that shows environment ``env`` of session ``session_id`` playing."""
    return f"{pages_url(conn)}watch/{session_id}?env={int(env)}"


def open_browser(url: str) -> bool:
    """Opens ``url`` in a graphical browser when this machine has one; returns whether it did.

    Only where a desktop is there to show it (a display on Linux, always on macOS and Windows):
    a text-mode browser cannot run the page, and a headless machine has nothing to open.
    """
    desktop = sys.platform in ("darwin", "win32") or bool(
        os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY")
    )
    if not desktop:
        return False
    try:
        return webbrowser.open(url)
    except webbrowser.Error:
        return False

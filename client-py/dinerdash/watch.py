"""The server's web pages (``--http-port``): their URLs from ``ServerInfo`` (the pages' host, or
the one the client reached when they listen on a wildcard; ``https`` over TLS), and a browser to
open them in, for ``python -m dinerdash watch`` and ``env.watch_url()`` (docs/watch.md).
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
    scheme = "https" if getattr(conn, "tls", False) else "http"
    return f"{scheme}://{join_host_port(host, info.http_port)}/"


def watch_url(conn: Connection, session_id: str, env: int = 0) -> str:
    """The URL of the page that shows environment ``env`` of session ``session_id`` playing."""
    return f"{pages_url(conn)}watch/{session_id}?env={int(env)}"


def open_browser(url: str) -> bool:
    """Opens ``url`` in a graphical browser where a desktop shows it (a display on Linux, always
    on macOS and Windows); returns whether it did."""
    desktop = sys.platform in ("darwin", "win32") or bool(
        os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY")
    )
    if not desktop:
        return False
    try:
        return webbrowser.open(url)
    except webbrowser.Error:
        return False

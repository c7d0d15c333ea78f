"""The one connection value the agents' runs hand down (:class:`dinerdash.ConnectOptions`): built
once from a function's ``connect=`` and its connection keywords, and a local server started for
it when it names none. Game keywords (``expert=...``) never ride in it."""

from __future__ import annotations

import dataclasses
import os
from collections.abc import Iterator
from contextlib import contextmanager
from typing import Any

from dinerdash import ConnectOptions
from dinerdash.server import LocalServer

__all__ = ["ConnectOptions", "options", "served"]


def options(
    connect: ConnectOptions | None, caller: str, address: Any = None, **connection: Any
) -> ConnectOptions:
    """``connect`` with ``address`` and the connection keywords (``timeout``, ``tls``, ...) put
    in, as :meth:`dinerdash.ConnectOptions.merged` does for the environments."""
    return ConnectOptions.merged(connect, caller, address=address, **connection)


@contextmanager
def served(connect: ConnectOptions) -> Iterator[tuple[ConnectOptions, LocalServer | None]]:
    """``(connect, server)``: as given when it (or ``DINERDASH_ADDRESS``) names a server, else
    pointed at a :class:`~dinerdash.server.LocalServer` started here and stopped on exit. Start
    it before any JAX work: forking a process while JAX's threads run is unsafe."""
    if connect.address is not None or os.environ.get("DINERDASH_ADDRESS"):
        yield connect, None
        return
    with LocalServer(connect.server_binary) as server:
        yield dataclasses.replace(connect, address=server.address), server

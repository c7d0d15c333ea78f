"""Where an env's sessions live: :class:`Endpoint`, the connections to its servers (or the local
server it started), a lost server waited for, and which servers were given up, taken back, added
or drain. A server keeps its index (``connections[i]`` is server ``i``).
"""

from __future__ import annotations

import dataclasses
import logging
import os
import time
from collections.abc import Callable

from . import connection
from .connection import Connection, ConnectOptions
from .errors import EnvClosed, ServiceTransportError
from .server import LocalServer

log = logging.getLogger("dinerdash")


class Endpoint:
    """Connections to one or more servers, and the local server this client started, if any."""

    def __init__(
        self, options: ConnectOptions, *, max_servers: int | None = None, pick: int | None = None
    ) -> None:
        self.options = options
        self.server: LocalServer | None = None
        self.connections: list[Connection] = []
        address = options.address
        address = (os.environ.get("DINERDASH_ADDRESS") or None) if address is None else address
        if address is not None:
            addresses = connection.resolve_replicas(address)
        else:
            # The local server is plaintext on loopback: TLS settings are for remote servers.
            self.options = dataclasses.replace(options, tls=False, tls_ca=False)
            self.server = LocalServer(options.server_binary)
            addresses = [self.server.address]
        if pick is not None:
            addresses = [addresses[pick % len(addresses)]]
        self.addresses = addresses[:max_servers]  # None: all
        #: The indices of the servers given up, in the order they were lost.
        self.given_up: list[int] = []
        #: The indices of the draining servers, in the order they said so (a dict's keys).
        self.draining: dict[int, None] = {}
        #: Servers given up for a failure (not drained), taken back or added, since the open.
        self.failovers = 0
        self.rejoins = 0
        #: Sessions whose transport changed (shared memory lost, or taken up again).
        self.transport_changes = 0
        try:
            for a in self.addresses:
                self.connections.append(self.options.connect(a))
        except BaseException:
            self.close()
            raise

    def reopen(self, index: int, create: Callable[[], object], lost: str, timeout: float) -> None:
        """Waits up to ``timeout`` seconds for server ``index`` to answer again, then calls
        ``create`` to open a new session there (``reconnect=True``)."""
        deadline = time.monotonic() + timeout
        while True:
            # Checked on every round: a dying process may still look alive at first.
            if self.server is not None and not self.server.is_running():
                self.server.start()
                self.connections[index].close()
                self.connections[index] = self.options.connect(self.server.address)
            conn = self.connections[index]
            if conn.wait_ready(min(1.0, max(0.0, deadline - time.monotonic()))):
                try:
                    create()
                    return
                except (ServiceTransportError, EnvClosed):
                    pass  # went away again between connecting and creating: keep waiting
            if index in self.given_up:  # meanwhile, a vector env's watch gave it up
                raise ServiceTransportError(
                    f"lost {lost}: {conn.address} was given up", address=conn.address
                )
            if time.monotonic() >= deadline:
                raise ServiceTransportError(
                    f"lost {lost} and could not reconnect to {conn.address} within {timeout:g} s",
                    address=conn.address,
                ) from None
            time.sleep(0.1)

    def live(self) -> list[int]:
        """The indices of the servers not given up."""
        return [i for i in range(len(self.connections)) if i not in self.given_up]

    def open_to_new(self) -> list[int]:
        """The indices of the servers that may take new sessions: live and not draining."""
        return [i for i in self.live() if i not in self.draining]

    def give_up(self, index: int, why: str | None = None) -> None:
        """Server ``index`` is lost (``why``; ``None``: drained): its channel is closed (its calls
        cancelled) and :meth:`live` leaves it out until :meth:`take_back`."""
        if index not in self.given_up:
            self.given_up.append(index)
            self.connections[index].close()
            self.draining.pop(index, None)
            if why is None:
                log.info("the server at %s drained; its environments moved", self.addresses[index])
            else:
                self.failovers += 1
                log.warning("gave up the server at %s: %s", self.addresses[index], why)

    def transport_changed(self, address: str, session: str, old: str, new: str, why: str) -> None:
        """A session's Steps changed transport (``old`` to ``new``): counted and logged once, as a
        warning, with ``why``."""
        self.transport_changes += 1
        log.warning(
            "session %s on %s steps over %s instead of %s from now on: %s",
            session,
            address,
            "shared memory" if new == "shm" else "gRPC",
            "shared memory" if old == "shm" else "gRPC",
            why,
        )

    def take_back(self, index: int, conn: Connection) -> None:
        """Server ``index``, given up, answers again: ``conn`` is its channel from now on."""
        self.given_up.remove(index)
        self.connections[index] = conn
        self.rejoins += 1
        log.info("took back the server at %s: it answers again", self.addresses[index])

    def add(self, conn: Connection) -> None:
        """A new server (``conn``'s address, e.g. a DNS name's new replica) taken in."""
        self.addresses.append(conn.address)
        self.connections.append(conn)
        self.rejoins += 1
        log.info("took in the server at %s: a new replica", conn.address)

    def drain(self, index: int, remaining: float | None) -> None:
        """Server ``index`` drains, ``remaining`` seconds left (``None``: unsaid): said once."""
        if index not in self.given_up and index not in self.draining:
            self.draining[index] = None
            log.info(
                "the server at %s drains (%s): its sessions move to the other servers",
                self.addresses[index],
                "deadline unknown" if remaining is None else f"{remaining:.1f} s left",
            )

    def close(self) -> None:
        for conn in self.connections:
            conn.close()
        self.connections = []
        if self.server is not None:
            self.server.stop()
            self.server = None

"""How one session's Steps travel: a :class:`Transport`, over gRPC (:class:`GrpcTransport`) or
through the session's shared-memory region (:class:`ShmTransport`, :mod:`dinerdash._shm`);
:func:`open_for` chooses one from the ``transport`` option and what the server offered. Reset and
every other call go over gRPC on both. Shared memory that ends under a Step raises
:class:`Detached`: the session core changes to gRPC, a counted and logged event (docs/shm.md).
"""

from __future__ import annotations

from typing import NoReturn

from . import _shm
from ._batch import Batch
from ._proto import pb
from .connection import Connection
from .errors import EnvClosed, ServiceError, ServiceTimeout

__all__ = ["Detached", "GrpcTransport", "ShmTransport", "Transport", "open_for"]


class Detached(Exception):
    """The shared-memory transport ended (private: caught by the session core). ``error``: the
    error to raise for this Step (a timeout, a cancellation), or ``None``: make it over gRPC."""

    def __init__(self, reason: str, error: ServiceError | None = None) -> None:
        super().__init__(reason)
        self.reason = reason
        self.error = error


class Transport:
    """One session's Steps: :meth:`step` returns a Step's Batch."""

    name: str
    views = False
    split = False

    def step(self, actions: bytes) -> Batch:
        raise NotImplementedError

    def close(self) -> None:
        pass


class GrpcTransport(Transport):
    """Steps as gRPC ``Step`` calls on the session's channel."""

    name = "grpc"

    def __init__(self, conn: Connection, session_id: str) -> None:
        self.conn = conn
        self.session_id = session_id

    def step(self, actions: bytes) -> Batch:
        request = pb.StepRequest(session_id=self.session_id, actions=actions)
        return Batch.from_pb(self.conn.call("Step", request))


class ShmTransport(Transport):
    """Steps through the session's shared-memory :class:`~dinerdash._shm.Channel`."""

    name = "shm"
    views = True
    split = True

    def __init__(self, channel: _shm.Channel) -> None:
        self.channel = channel

    def step(self, actions: bytes) -> Batch:
        if not self.send(actions):
            self._closed()
        return self.receive()

    def send(self, actions: bytes) -> bool:
        """Sends a Step and returns at once; False when the doorbell closed (nothing sent)."""
        return self.channel.send(actions)

    def ready(self, timeout: float | None) -> bool:
        """Whether the reply of the Step :meth:`send` sent is in within ``timeout``."""
        return self.channel.ready(timeout)

    def receive(self) -> Batch:
        """The Batch of the Step :meth:`send` sent; raises :class:`Detached` as :meth:`step`."""
        try:
            batch = self.channel.receive()
        except ServiceTimeout as e:
            raise Detached("a Step over shared memory timed out", e) from None
        except EnvClosed as e:
            raise Detached("a Step over shared memory was cancelled", e) from None
        if batch is None:
            self._closed()
        return batch

    def _closed(self) -> NoReturn:
        raise Detached(
            f"the doorbell of the server at {self.channel.address} closed under a Step (the "
            "server died, drained or forgot the session)"
        )

    def close(self) -> None:
        self.channel.close()


def open_for(offer: _shm.Offer | None, conn: Connection, option: str) -> Transport:
    """The transport of the session ``offer`` describes: shared memory when ``option``
    (``ConnectOptions.transport``) allows it and it opens (:func:`dinerdash._shm.attach`, which
    says why not, or raises for ``"shm"``), else gRPC."""
    channel = _shm.attach(offer, conn, option)
    if channel is None:
        return GrpcTransport(conn, offer.session_id if offer is not None else "")
    return ShmTransport(channel)

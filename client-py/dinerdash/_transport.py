"""How one session's Steps travel: a :class:`Transport`, over gRPC (:class:`GrpcTransport`) or
through the session's shared-memory region (:class:`ShmTransport`, :mod:`dinerdash._shm`).
Each returns a :class:`~dinerdash._batch.Batch`; a session core holds one (:func:`open_for`
chooses it from the ``transport`` option and what the server offered). Reset and every other
call go over gRPC on both.

The shared-memory transport ends when its doorbell closes under a Step (the server died,
drained, or forgot the session) or a Step is abandoned (timed out, cancelled: its late reply
must not answer the next one). It then raises :class:`Detached`, a private signal that never
leaves the session core: the core changes to gRPC, which is an event (counted, logged once as a
warning with the reason: :meth:`Endpoint.transport_changed
<dinerdash._endpoint.Endpoint.transport_changed>`); so is shared memory taken up again by a
session reopened after a reconnect. ``envs.transports`` reads what each session uses now.
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
    error to raise for this Step (a timeout, a cancellation), or ``None`` when the Step is to be
    made over gRPC, whose answer is then the one the gRPC path would have given."""

    def __init__(self, reason: str, error: ServiceError | None = None) -> None:
        super().__init__(reason)
        self.reason = reason
        self.error = error


class Transport:
    """One session's data plane: :meth:`step` returns the Batch of a Step; :meth:`reset` (gRPC
    on every transport) a Reset's. ``views``: whether a Batch's arrays are views that the next
    Step overwrites (the caller copies what it keeps past that)."""

    name = "grpc"
    views = False
    split = False

    def __init__(self, conn: Connection, session_id: str) -> None:
        self.conn = conn
        self.session_id = session_id

    def reset(self, request: pb.ResetRequest) -> Batch:
        return Batch.from_pb(self.conn.call("Reset", request))

    def step(self, actions: bytes) -> Batch:
        request = pb.StepRequest(session_id=self.session_id, actions=actions)
        return Batch.from_pb(self.conn.call("Step", request))

    def close(self) -> None:
        pass


class GrpcTransport(Transport):
    """Steps as gRPC ``Step`` calls on the session's channel."""


class ShmTransport(Transport):
    """Steps through the session's shared-memory :class:`~dinerdash._shm.Channel`: its Batches'
    arrays are views of the region, valid until the next Step is sent."""

    name = "shm"
    views = True
    #: A Step can be rung for (:meth:`send`) and collected later (:meth:`receive`) with no
    #: thread: the server steps while the caller works (``step_async`` / ``step_wait``).
    split = True

    def __init__(self, conn: Connection, session_id: str, channel: _shm.Channel) -> None:
        super().__init__(conn, session_id)
        self.channel = channel

    def step(self, actions: bytes) -> Batch:
        if not self.send(actions):
            self._closed()
        return self.receive()

    def send(self, actions: bytes) -> bool:
        """Rings for a Step and returns at once (the server steps meanwhile); :meth:`receive`
        returns its Batch. False when the doorbell closed: nothing was sent, and :meth:`step`
        would raise :class:`Detached`."""
        return self.channel.send(actions)

    def ready(self, timeout: float | None) -> bool:
        """Whether the reply of the Step :meth:`send` rang for is in within ``timeout``."""
        return self.channel.ready(timeout)

    def receive(self) -> Batch:
        """The Batch of the Step :meth:`send` rang for; raises :class:`Detached` as :meth:`step`."""
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
            f"the doorbell of the server at {self.conn.address} closed under a Step (the "
            "server died, drained or forgot the session)"
        )

    def close(self) -> None:
        self.channel.close()


def open_for(offer: _shm.Offer | None, conn: Connection, option: str) -> Transport:
    """The transport of the session ``offer`` describes: shared memory when ``option``
    (``ConnectOptions.transport``) allows it and it opens (:func:`dinerdash._shm.attach`, which
    says why not, or raises for ``"shm"``), else gRPC."""
    session_id = offer.session_id if offer is not None else ""
    channel = _shm.attach(offer, conn, option)
    if channel is None:
        return GrpcTransport(conn, session_id)
    return ShmTransport(conn, session_id, channel)

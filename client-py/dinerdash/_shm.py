"""How a session's Steps travel: a :class:`Transport`, over gRPC (:class:`GrpcTransport`) or
through shared memory (:class:`ShmTransport`, the same-host data plane of docs/shm.md), chosen by
:func:`open_for`, which opens a session's :class:`Channel` (the doorbell, its peer checked, and the
mapped region) or says why not; Reset and every other call go over gRPC. Shared memory that ends
under a Step raises :class:`Detached`: the session core changes to gRPC.
"""

from __future__ import annotations

import array
import dataclasses
import functools
import ipaddress
import logging
import math
import mmap
import os
import select
import socket
import struct
import sys
import time
from typing import Any

import grpc
import numpy as np

from ._batch import FIELDS as _SHAPES
from ._batch import Batch
from ._proto import pb
from .connection import Connection, split_host_port
from .errors import ServiceError, ServiceTransportError

#: "DDsh" and the layout version this client reads (``server/src/shm/layout.rs``).
_MAGIC, _VERSION = struct.unpack("<I", b"DDsh")[0], 2
#: The region's arrays, in order: the ``actions`` the client writes, then the Batch's fields
#: (:data:`dinerdash._batch.FIELDS`, the one table).
FIELDS = ("actions", *_SHAPES)
_TABLE, _LENGTHS = 32, 256
#: The last reply's ``drain_remaining_ms``, right after the lengths.
_DRAIN_AT, _DRAIN = _LENGTHS + 4 * len(FIELDS), struct.Struct("<I")
_CODES = {c.value[0]: c for c in grpc.StatusCode}
#: How often a Step waiting for its reply looks at its deadline and its connection.
_TICK = 0.25
#: A Step whose last reply came within this many seconds polls this long before it sleeps in
#: ``recv`` (why: docs/shm.md#why-each-side-polls-a-little-before-it-sleeps).
_SPIN = 100e-6

log = logging.getLogger("dinerdash")

#: SO_PEERCRED's ``struct ucred``: pid (signed), uid and gid (unsigned).
_UCRED = struct.Struct("iII")


@dataclasses.dataclass(frozen=True)
class Offer:
    """What a CreateSession, Fork or Restore reply told its caller about the session's shared
    memory. ``secret`` is the hello's credential: it is never shown (``repr``) nor logged."""

    session_id: str
    #: The abstract socket's name ("" when the server offers none).
    doorbell: str
    #: The session's secret (empty from a server older than the doorbell's peer check).
    secret: bytes = dataclasses.field(repr=False)
    #: The server's pid as its reply told it (0 from such an older server).
    pid: int

    @classmethod
    def of(cls, reply: Any) -> Offer:
        """What ``reply`` (CreateSession's, Fork's or Restore's) offers."""
        return cls(reply.session_id, reply.shm_doorbell, reply.shm_secret, reply.shm_server_pid)


class _Untrusted(Exception):
    """The doorbell's peer is not the server that made the offer: nothing was sent to it."""


class Detached(Exception):
    """The shared-memory transport ended (private: caught by the session core). ``error``: the
    error to raise for this Step (a timeout, a cancellation), or ``None``: make it over gRPC."""

    def __init__(self, reason: str, error: ServiceError | None = None) -> None:
        super().__init__(reason)
        self.error = error


@functools.lru_cache(maxsize=64)
def _on_this_host(address: str) -> bool:
    """Whether every address ``address``'s host resolves to is loopback or this host's own."""
    try:
        host, port = split_host_port(address)
        infos = socket.getaddrinfo(host, port, type=socket.SOCK_STREAM)
    except (OSError, ValueError, UnicodeError):
        return False
    for family, _, _, _, sockaddr in infos:
        try:  # not loopback: one of this host's addresses if a socket binds to it
            if not ipaddress.ip_address(sockaddr[0].partition("%")[0]).is_loopback:
                with socket.socket(family, socket.SOCK_DGRAM) as probe:
                    probe.bind((sockaddr[0], 0, *sockaddr[2:]))
        except (ValueError, OSError):
            return False
    return bool(infos)


def _check_peer(sock: socket.socket, offer: Offer) -> None:
    """Raises :class:`_Untrusted` unless the doorbell's peer (``SO_PEERCRED``, read before anything
    is sent) runs as this user and is the process the server's reply named."""
    raw = sock.getsockopt(socket.SOL_SOCKET, socket.SO_PEERCRED, _UCRED.size)
    pid, uid, _ = _UCRED.unpack(raw)
    if uid != os.geteuid():
        raise _Untrusted(
            f"the doorbell {offer.doorbell!r} is answered by uid {uid}, not this user (uid "
            f"{os.geteuid()}): another user's process, or a server running as another user"
        )
    if pid != offer.pid:
        raise _Untrusted(
            f"the doorbell {offer.doorbell!r} is answered by pid {pid}, not the server's pid "
            f"{offer.pid} (another process holds its name, or the server runs in another pid "
            "namespace, e.g. another container)"
        )


class Channel:
    """One session's doorbell socket and mapped region."""

    def __init__(self, offer: Offer, conn: Connection) -> None:
        self.conn = conn
        self.timeout = conn.timeout
        sock = socket.socket(socket.AF_UNIX, socket.SOCK_SEQPACKET | socket.SOCK_CLOEXEC)
        try:
            sock.settimeout(conn.timeout)
            sock.connect("\0" + offer.doorbell)
            _check_peer(sock, offer)
            sock.sendall(b"H" + offer.session_id.encode() + offer.secret)
            reply, ancillary, _, _ = sock.recvmsg(65536, socket.CMSG_SPACE(4))
            fds = array.array("i")
            for level, kind, data in ancillary:
                if level == socket.SOL_SOCKET and kind == socket.SCM_RIGHTS:
                    fds.frombytes(data[: len(data) - len(data) % fds.itemsize])
            if reply[:1] != b"R" or len(fds) != 1:
                for fd in fds:
                    os.close(fd)
                raise self._refusal("shared memory", reply)
            try:
                self.mm = mmap.mmap(fds[0], 0)
            finally:
                os.close(fds[0])
        except BaseException:
            sock.close()
            raise
        # Blocking from here, waking every _TICK to see the deadline and a closed connection.
        sock.settimeout(None)
        tick = int(min(conn.timeout, _TICK) * 1e6)  # microseconds, under a second
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVTIMEO, struct.pack("ll", 0, tick))
        self.sock = sock
        magic, version, n, fields = struct.unpack_from("<IIII", self.mm, 0)
        if (magic, version, fields) != (_MAGIC, _VERSION, len(FIELDS)):
            self.close()
            raise ServiceTransportError(
                f"the server at {self.conn.address} speaks shared-memory layout {version}, this "
                f"client {_VERSION}",
                address=self.conn.address,
            )
        self.num_envs = n
        self._offsets = [
            struct.unpack_from("<I", self.mm, _TABLE + 8 * i)[0] for i in range(len(FIELDS))
        ]
        self._lengths = np.frombuffer(self.mm, dtype="<u4", count=len(FIELDS), offset=_LENGTHS)
        #: The lengths of the last reply, and the views of the region they gave.
        self._known: tuple[bytes, dict[str, np.ndarray]] = (b"", {})
        #: Whether the last reply came within _SPIN: then the next one is polled for.
        self._spin_next = False
        #: When the last Step was sent (:func:`time.perf_counter`; the bench times from it).
        self.sent = 0.0

    def _refusal(self, method: str, reply: bytes) -> ServiceError:
        """The typed exception of an ``E`` reply (code, message, ``google.rpc.Status``)."""
        if reply[:1] != b"E" or len(reply) < 9:
            return ServiceTransportError(
                f"{method}: unexpected reply {bytes(reply[:16])!r} from the doorbell",
                address=self.conn.address,
            )
        code, size = struct.unpack_from("<II", reply, 1)
        message = bytes(reply[9 : 9 + size]).decode("utf-8", "replace")
        code = _CODES.get(code, grpc.StatusCode.UNKNOWN)
        return self.conn.error_for(method, code, message, status=bytes(reply[9 + size :]) or None)

    def send(self, actions: bytes) -> bool:
        """Writes a Step's ``actions`` into the region and rings; False when the doorbell closed."""
        offset = self._offsets[0]
        self.mm[offset : offset + len(actions)] = actions
        try:
            self.sock.send(b"S")
        except OSError:
            return False
        self.sent = time.perf_counter()
        return True

    def ready(self, timeout: float | None) -> bool:
        """Whether the outcome of the Step :meth:`send` rang for (its reply, the doorbell's end,
        the connection closed, or its deadline passed) is in within ``timeout`` seconds (``None``:
        waits for it), for :meth:`receive` to return or raise at once."""
        now = time.perf_counter()
        until = None if timeout is None else now + timeout
        poller = select.poll()
        poller.register(self.sock, select.POLLIN | select.POLLHUP | select.POLLERR)
        while True:
            left = self.sent + self.timeout - now
            if self.conn._closed or left <= 0:
                return True
            wait = min(_TICK, left) if until is None else min(_TICK, left, until - now)
            if poller.poll(max(0, math.ceil(wait * 1000))):
                return True
            now = time.perf_counter()
            if until is not None and now >= until:
                return False

    def receive(self) -> Batch:
        """The reply of the Step :meth:`send` rang for: its Batch (views of the region, valid
        until the next Step) or its typed refusal raised; :class:`Detached` when the doorbell
        closed, the Step timed out or the connection was closed (given up)."""
        sent = self.sent
        reply = self._poll(sent) if self._spin_next else None
        while reply is None:
            closed = self.conn._closed  # given up: as a gRPC call cancelled by its channel
            try:
                reply = self.sock.recv(65536, socket.MSG_DONTWAIT if closed else 0)
                break
            except BlockingIOError:
                if closed or time.perf_counter() - sent >= self.timeout:
                    code = grpc.StatusCode["CANCELLED" if closed else "DEADLINE_EXCEEDED"]
                    why = "was cancelled" if closed else "timed out"
                    error = self.conn.error_for("Step", code, "")
                    raise Detached(f"a Step over shared memory {why}", error) from None
            except OSError:
                raise self.gone() from None
        self._spin_next = time.perf_counter() - sent < _SPIN
        if reply != b"K":
            raise self._refusal("Step", reply) if reply else self.gone()
        lengths = self._lengths.tobytes()
        known, views = self._known
        if lengths != known:  # the reply's arrays as read-only views of the region, made anew
            views = {}
            for name, lo, size in zip(FIELDS, self._offsets, self._lengths.tolist(), strict=True):
                if size and name != "actions":
                    dtype, width = _SHAPES[name]
                    count = size // np.dtype(dtype).itemsize
                    view = np.frombuffer(self.mm, dtype=dtype, count=count, offset=lo)
                    views[name] = view.reshape(-1, width) if width > 1 else view
                    views[name].flags.writeable = False
            self._known = (lengths, views)
        (drain,) = _DRAIN.unpack_from(self.mm, _DRAIN_AT)
        return Batch(self.num_envs, views, drain)

    def _poll(self, sent: float) -> bytes | None:
        """The reply if it comes within _SPIN of ``sent`` (polled, no sleep), or ``None``."""
        sock, until = self.sock, sent + _SPIN
        while True:
            try:
                return sock.recv(65536, socket.MSG_DONTWAIT)
            except BlockingIOError:
                if time.perf_counter() >= until:
                    return None
            except OSError:
                return None

    def gone(self) -> Detached:
        return Detached(
            f"the doorbell of the server at {self.conn.address} closed under a Step (the server "
            "died, drained or forgot the session)"
        )

    def close(self) -> None:
        self.sock.close()
        self._lengths = None  # the views of the mapping this side keeps
        self._known = (b"", {})
        try:
            self.mm.close()
        except BufferError:  # a view still exported: the mapping goes with it
            pass


def open_for(offer: Offer | None, conn: Connection, transport: str) -> Transport:
    """The transport of the session ``offer`` describes, on the server of ``conn``: shared memory
    when ``transport`` allows it and its :class:`Channel` opens; else gRPC, why logged at debug
    level (raised as a ``ServiceTransportError`` for ``transport="shm"``)."""
    if transport == "grpc" or offer is None:
        return GrpcTransport(conn, offer.session_id if offer is not None else "")
    why = None
    if sys.platform != "linux":
        why = "shared memory needs Linux"
    elif not offer.doorbell:
        why = (
            f"the server at {conn.address} offers no shared memory (--max-shm-sessions 0, not "
            "on Linux, or a server older than the shared-memory data plane)"
        )
    elif not offer.secret or not offer.pid:
        why = (
            f"the server at {conn.address} names a doorbell but no session secret or pid (a "
            "server older than the doorbell's peer check): shared memory is not trusted there"
        )
    elif not _on_this_host(conn.address):
        why = (
            f"the server at {conn.address} is not on this machine (its address is neither "
            "loopback nor one of this host's): shared memory needs client and server on one host"
        )
    else:
        try:
            return ShmTransport(Channel(offer, conn))
        except (ConnectionRefusedError, FileNotFoundError):
            why = (
                f"the server at {conn.address} is not on this machine (or runs in another "
                "network namespace, e.g. another container): shared memory needs client and "
                "server on one host"
            )
        except _Untrusted as e:
            why = f"the doorbell is not the server's: {e}"
        except ServiceError as e:
            why = f"the server refused shared memory: {e.details}"
        except OSError as e:
            why = f"the doorbell failed: {e}"
    log.debug("session %s steps over gRPC: %s", offer.session_id, why)
    if transport == "shm":
        raise ServiceTransportError(
            f"transport='shm': {why}; use transport='auto' to fall back to gRPC",
            address=conn.address,
        )
    return GrpcTransport(conn, offer.session_id)


class Transport:
    """One session's Steps: :meth:`step` returns a Step's Batch. ``views``: its Batches are views
    of a region, valid until the next Step, and a Step may be sent and received apart."""

    name: str
    views = False

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
    """Steps through the session's shared-memory :class:`Channel`."""

    name = "shm"
    views = True

    def __init__(self, channel: Channel) -> None:
        self.channel = channel
        #: A Step sent (False: the doorbell closed, nothing sent), its reply in by a timeout, and
        #: its Batch (:meth:`Channel.receive`).
        self.send, self.ready, self.receive = channel.send, channel.ready, channel.receive

    def step(self, actions: bytes) -> Batch:
        if not self.send(actions):
            raise self.channel.gone()
        return self.receive()

    def close(self) -> None:
        self.channel.close()

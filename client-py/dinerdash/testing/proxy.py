"""``FaultProxy``: a TCP proxy on 127.0.0.1 that puts network faults between a client and a server
(docs/client.md#testing-your-own-training-code). Stdlib only: an asyncio event loop in a daemon
thread; the methods may be called from any thread and take effect before they return.
"""

from __future__ import annotations

import asyncio
import collections
import socket
import struct
import threading
from collections.abc import Callable
from typing import Any

__all__ = ["FaultProxy"]

_NORMAL, _BLACKHOLE, _CUT = "normal", "blackhole", "cut"
#: Bytes buffered toward one side before the proxy stops reading from the other.
_HIGH_WATER = 1 << 20


def _rst(transport: asyncio.BaseTransport | None) -> None:
    """Closes ``transport`` with a TCP reset rather than a FIN: ``SO_LINGER`` on, 0 seconds."""
    if transport is None:
        return
    sock = transport.get_extra_info("socket")
    if sock is not None:
        try:
            sock.setsockopt(socket.SOL_SOCKET, socket.SO_LINGER, struct.pack("ii", 1, 0))
        except OSError:
            pass
    transport.abort()


class _Side(asyncio.Protocol):
    """One socket of a proxied connection: the client's (accepted) or the server's (dialled)."""

    def __init__(self, link: _Link) -> None:
        self.link = link
        self.transport: asyncio.Transport | None = None
        self.peer: _Side | None = None
        #: (due time, bytes) waiting for their delivery to this side (the latency).
        self.pending: collections.deque[tuple[float, bytes]] = collections.deque()
        self.timer: asyncio.TimerHandle | None = None
        #: Bytes that arrived before :attr:`peer` was known.
        self.early: list[bytes] = []
        #: The socket is closed (``connection_lost`` was called).
        self.gone = False

    def connection_made(self, transport: asyncio.BaseTransport) -> None:
        self.transport = transport  # type: ignore[assignment]
        transport.set_write_buffer_limits(high=_HIGH_WATER)  # type: ignore[attr-defined]

    def data_received(self, data: bytes) -> None:
        proxy = self.link.proxy
        if proxy._mode == _BLACKHOLE:
            self.link.swallowed = True
            return
        if self.peer is not None:
            self.peer.deliver(data, proxy._latency)
        else:  # the server's first bytes, before the link is joined up
            self.early.append(data)

    def deliver(self, data: bytes, latency: float) -> None:
        """Writes ``data`` to this side now, or ``latency`` seconds after it arrived, never before
        bytes that arrived earlier."""
        if latency <= 0 and not self.pending:
            self.write(data)
            return
        loop = self.link.proxy._loop
        due = loop.time() + max(latency, 0.0)
        if self.pending:
            due = max(due, self.pending[-1][0])
        self.pending.append((due, data))
        if self.timer is None:
            self.timer = loop.call_at(self.pending[0][0], self._flush)

    def _flush(self) -> None:
        self.timer = None
        loop = self.link.proxy._loop
        now = loop.time()
        while self.pending and self.pending[0][0] <= now:
            self.write(self.pending.popleft()[1])
        if self.pending:
            self.timer = loop.call_at(self.pending[0][0], self._flush)

    def write(self, data: bytes) -> None:
        if self.transport is not None and not self.transport.is_closing():
            self.transport.write(data)

    def pause_writing(self) -> None:  # this side is slow to take bytes: stop reading the other
        if self.peer is not None and self.peer.transport is not None:
            self.peer.transport.pause_reading()

    def resume_writing(self) -> None:
        if self.peer is not None and self.peer.transport is not None:
            self.peer.transport.resume_reading()

    def eof_received(self) -> bool:
        # A half close passes through, after the bytes still delayed.
        if self.peer is not None:
            self.peer.close_after_pending(half=True)
        return True

    def close_after_pending(self, half: bool = False) -> None:
        """Closes this side (``half``: only its writing end) once its delayed bytes are out."""
        if self.transport is None or self.transport.is_closing():
            return
        if self.pending:
            loop = self.link.proxy._loop
            loop.call_at(self.pending[-1][0], self.close_after_pending, half)
        elif half and self.transport.can_write_eof():
            self.transport.write_eof()
        else:
            self.transport.close()

    def connection_lost(self, exc: Exception | None) -> None:
        if self.timer is not None:
            self.timer.cancel()
            self.timer = None
        self.gone = True
        self.link.lost(self, exc)

    def drop(self) -> None:
        """Resets this side now, dropping the bytes still delayed."""
        if self.timer is not None:
            self.timer.cancel()
            self.timer = None
        self.pending.clear()
        _rst(self.transport)


class _ClientSide(_Side):
    """The accepted socket: the link dials the target when it arrives."""

    def connection_made(self, transport: asyncio.BaseTransport) -> None:
        super().connection_made(transport)
        self.link.accepted()

    def data_received(self, data: bytes) -> None:
        self.link.proxy._count_from_client(len(data))
        super().data_received(data)


class _Link:
    """One proxied connection: the client's side and the server's side."""

    def __init__(self, proxy: FaultProxy) -> None:
        self.proxy = proxy
        self.client: _Side = _ClientSide(self)
        self.server: _Side | None = None
        #: Bytes were swallowed by a black hole: the stream has a hole and cannot be healed.
        self.swallowed = False
        self.closed = False

    def accepted(self) -> None:
        if self.proxy._mode == _CUT:
            self.reset()
            return
        self.proxy._links.add(self)
        self.proxy._loop.create_task(self.dial())

    async def dial(self) -> None:
        """Connects to the target; the client's side is read only once this is done."""
        assert self.client.transport is not None
        self.client.transport.pause_reading()
        try:
            host, port = self.proxy._target
            _, server = await self.proxy._loop.create_connection(lambda: _Side(self), host, port)
        except OSError:
            self.reset()  # as a server that refuses: the client sees its connection reset
            return
        if self.closed:
            server.drop()
            return
        self.server = server
        server.peer, self.client.peer = self.client, server
        for data in server.early:
            self.client.deliver(data, self.proxy._latency)
        server.early.clear()
        if not self.client.transport.is_closing():
            self.client.transport.resume_reading()

    def lost(self, side: _Side, exc: Exception | None) -> None:
        """One side closed: a reset is passed on at once, a close after the bytes still due."""
        other = self.server if side is self.client else self.client
        if other is not None:
            if exc is not None:
                other.drop()
            else:
                other.close_after_pending()
        if self.client.gone and (self.server is None or self.server.gone):
            self.closed = True
            self.proxy._links.discard(self)

    def reset(self) -> None:
        self.closed = True
        self.client.drop()
        if self.server is not None:
            self.server.drop()
        self.proxy._links.discard(self)


class FaultProxy:
    """A TCP proxy from ``127.0.0.1:PORT`` (:attr:`address`) to ``target`` (``"host:port"``) whose
    faults can be switched on and off while clients use it."""

    def __init__(self, target: str, *, host: str = "127.0.0.1", port: int = 0) -> None:
        target_host, _, target_port = target.rpartition(":")
        if not target_host or not target_port.isdigit():
            raise ValueError(f"target: expected 'host:port', got {target!r}")
        self.target = target
        self._target = (target_host.strip("[]"), int(target_port))
        self._mode = _NORMAL
        self._latency = 0.0
        self._links: set[_Link] = set()
        self._from_clients = 0
        self._loop = asyncio.new_event_loop()
        self._server: asyncio.AbstractServer | None = None
        self._thread = threading.Thread(
            target=self._loop.run_forever, name=f"dinerdash-fault-proxy-{target}", daemon=True
        )
        self._thread.start()
        try:
            self._server = self._call_async(
                self._loop.create_server(lambda: self._accept(), host, port)
            )
        except BaseException:
            self._stop_loop()
            raise
        sockname = self._server.sockets[0].getsockname()
        #: ``"127.0.0.1:PORT"``: where clients connect instead of ``target``.
        self.address = f"{sockname[0]}:{sockname[1]}"
        self.port: int = sockname[1]

    def _accept(self) -> _Side:
        return _Link(self).client

    def _call_async(self, coroutine: Any) -> Any:
        return asyncio.run_coroutine_threadsafe(coroutine, self._loop).result(timeout=30)

    def _call(self, fn: Callable[[], Any]) -> Any:
        """Runs ``fn`` on the proxy's loop and returns its result: a fault is on when this
        returns."""
        if self._loop.is_closed():
            raise RuntimeError(f"FaultProxy({self.target!r}) is closed")

        async def run() -> Any:
            return fn()

        return self._call_async(run())

    @property
    def connections(self) -> int:
        """Connections open through the proxy now."""
        return self._call(lambda: len(self._links))

    @property
    def bytes_from_clients(self) -> int:
        """Bytes read from clients' connections since the proxy started, forwarded, delayed or
        swallowed; never decreases. A call has reached the proxy once the count grew past its
        value before the call (HTTP/2 pings count too: read it after earlier calls returned)."""
        return self._from_clients

    def _count_from_client(self, n: int) -> None:
        self._from_clients += n  # on the proxy's loop

    @property
    def mode(self) -> str:
        """``"normal"``, ``"blackhole"`` or ``"cut"``."""
        return self._mode

    def latency(self, seconds: float) -> None:
        """Delays every chunk by ``seconds`` in each direction from now on (0: none)."""
        if not seconds >= 0:
            raise ValueError(f"latency: expected seconds >= 0, got {seconds!r}")
        self._call(lambda: setattr(self, "_latency", float(seconds)))

    def blackhole(self) -> None:
        """Swallows every byte both ways; connections stay open, new ones are accepted."""
        self._call(lambda: setattr(self, "_mode", _BLACKHOLE))

    def reset(self) -> None:
        """Closes every open connection with a TCP reset, both sides; new connections work."""
        self._call(self._reset_links)

    def cut(self) -> None:
        """Resets every open connection and every new one until :meth:`heal`."""

        def on() -> None:
            self._mode = _CUT
            self._reset_links()

        self._call(on)

    def heal(self) -> None:
        """Plain forwarding again, without latency; connections that lost bytes to
        :meth:`blackhole` are reset."""

        def off() -> None:
            self._mode, self._latency = _NORMAL, 0.0
            self._reset_links(lambda link: link.swallowed)

        self._call(off)

    def _reset_links(self, which: Callable[[_Link], bool] = lambda link: True) -> None:
        """Resets the links ``which`` picks (on the proxy's loop)."""
        for link in list(self._links):
            if which(link):
                link.reset()

    def close(self) -> None:
        """Stops listening and resets every connection; safe to call twice."""
        if self._loop.is_closed():
            return

        async def shutdown() -> None:
            if self._server is not None:
                self._server.close()
            self._reset_links()
            await asyncio.sleep(0)  # let the aborts run

        try:
            self._call_async(shutdown())
        finally:
            self._stop_loop()

    def _stop_loop(self) -> None:
        self._loop.call_soon_threadsafe(self._loop.stop)
        self._thread.join(timeout=10)
        if not self._thread.is_alive():
            self._loop.close()

    def __enter__(self) -> FaultProxy:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def __repr__(self) -> str:
        return (
            f"FaultProxy({self.address} -> {self.target}, {self._mode}, latency={self._latency:g})"
        )

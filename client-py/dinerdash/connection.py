"""The channel to a DinerDash server and the one call wrapper every RPC goes through:
:class:`ConnectOptions`, the channel's options, the address rules, the deadline, TLS, the typed
errors (:mod:`dinerdash.errors`), and retries: the channel's service config and one helper for
what it cannot express (docs/client.md#retries, #the-channel).
"""

from __future__ import annotations

import dataclasses
import ipaddress
import json
import math
import numbers
import os
import socket
import ssl
import time
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass
from typing import Any

import grpc

from ._proto import pb, pb_grpc
from ._version import warn_if_other_version
from .errors import (
    DETAILS_KEY,
    EnvClosed,
    ServiceError,
    ServiceTimeout,
    ServiceTransportError,
    TLSMismatch,
    error_for_status,
    trailer,
)

__all__ = [
    "CHANNEL_OPTIONS",
    "CONNECT_FIELDS",
    "DEFAULT_PORT",
    "DEFAULT_TIMEOUT",
    "ConnectOptions",
    "Connection",
    "call_timeout",
    "parse_addresses",
    "resolve_replicas",
    "service_config",
]

#: The ways Steps may travel (:attr:`ConnectOptions.transport`).
TRANSPORTS = ("auto", "shm", "grpc")

#: The port a server listens on when none is given (and the one the docker image exposes).
DEFAULT_PORT = 50051

#: Seconds a call may take when neither ``timeout=`` nor ``DINERDASH_TIMEOUT`` says.
DEFAULT_TIMEOUT = 60.0
#: Seconds a connection waits for its server to answer at first, unless the call timeout is shorter.
CONNECT_TIMEOUT = 10.0

#: The service whose methods the channel's service config retries.
SERVICE = "dinerdash.v1.DinerDash"
#: Calls never retried: a Step applied whose reply was lost would be applied twice.
NOT_RETRIED = frozenset({"Step", "StepStream"})
#: Calls retried by :meth:`Connection._retrying` only (why: docs/client.md#retries).
BY_HAND = frozenset({"Rollout", "CloseSession"})
#: The most retries the channel makes of one call: gRPC caps ``retryPolicy.maxAttempts`` at 5.
CHANNEL_MAX_RETRIES = 4
#: The trailer by which a server pushes back on retries (gRFC A6): negative means do not retry.
RETRY_PUSHBACK = "grpc-retry-pushback-ms"

#: Why each is set: docs/client.md#the-channel.
CHANNEL_OPTIONS: list[tuple[str, Any]] = [
    ("grpc.max_receive_message_length", 256 * 1024 * 1024),
    ("grpc.max_send_message_length", 256 * 1024 * 1024),
    ("grpc.enable_retries", 1),
    ("grpc.service_config_disable_resolution", 1),
    ("grpc.per_rpc_retry_buffer_size", 256 * 1024 * 1024),
    ("grpc.initial_reconnect_backoff_ms", 100),
    ("grpc.min_reconnect_backoff_ms", 100),
    ("grpc.max_reconnect_backoff_ms", 2000),
    ("grpc.use_local_subchannel_pool", 1),
    ("grpc.enable_http_proxy", 0),
    ("grpc.keepalive_time_ms", 20_000),
    ("grpc.keepalive_timeout_ms", 10_000),
    ("grpc.keepalive_permit_without_calls", 0),
    ("grpc.http2.max_pings_without_data", 0),
]


def _duration(seconds: float) -> str:
    """``seconds`` as a protobuf JSON Duration, at least a millisecond (gRPC wants it > 0)."""
    return f"{max(seconds, 0.001):.9f}s"


def service_config(retries: int, retry_backoff: float) -> str:
    """The channel's service config (JSON): ``UNAVAILABLE`` retried up to ``retries`` times
    (at most 4), after ``retry_backoff`` seconds doubled at each, but for those not retried."""
    retries = min(retries, CHANNEL_MAX_RETRIES)
    if retries <= 0:
        return json.dumps({"methodConfig": []})
    policy = {
        "maxAttempts": retries + 1,
        "initialBackoff": _duration(retry_backoff),
        "maxBackoff": _duration(retry_backoff * 2 ** (CHANNEL_MAX_RETRIES - 1)),
        "backoffMultiplier": 2,
        "retryableStatusCodes": ["UNAVAILABLE"],
    }
    # A method's own entry wins over its service's: these have no retry policy.
    methods = [{"service": SERVICE, "method": m} for m in sorted(NOT_RETRIED | BY_HAND)]
    configs = [{"name": [{"service": SERVICE}], "retryPolicy": policy}, {"name": methods}]
    return json.dumps({"methodConfig": configs}, separators=(",", ":"))


def call_timeout(timeout: float | None) -> float:
    """The deadline of each call, in seconds: ``timeout``, else ``DINERDASH_TIMEOUT``, else
    :data:`DEFAULT_TIMEOUT`. Always finite and positive."""
    if timeout is None:
        text = os.environ.get("DINERDASH_TIMEOUT", "").strip() or str(DEFAULT_TIMEOUT)
        try:
            timeout = float(text)
        except ValueError:
            raise ValueError(f"DINERDASH_TIMEOUT: expected seconds, got {text!r}") from None
    timeout = float(timeout)
    if not 0 < timeout < float("inf"):
        raise ValueError(f"timeout: expected a positive number of seconds, got {timeout!r}")
    return timeout


def tls_credentials(
    tls: bool, tls_ca: str | os.PathLike | bool | None
) -> grpc.ChannelCredentials | None:
    """The channel credentials (``None``: plaintext) for ``tls`` and ``tls_ca`` (a CA file;
    ``None``: ``DINERDASH_TLS_CA``; ``False``: none, whatever the environment says)."""
    if tls_ca is None:
        tls_ca = os.environ.get("DINERDASH_TLS_CA") or None
    if tls_ca is not None and tls_ca is not False:
        try:
            with open(tls_ca, "rb") as f:
                pem = f.read()
        except OSError as e:
            raise FileNotFoundError(f"tls_ca: cannot read {os.fspath(tls_ca)!r}: {e}") from None
        return grpc.ssl_channel_credentials(root_certificates=pem)
    if tls:
        return grpc.ssl_channel_credentials()
    return None


def _speaks_tls(address: str, timeout: float = 2.0) -> bool | None:
    """Whether the server at ``address`` completes a TLS handshake (certificate not checked):
    ``None`` when nothing accepts a TCP connection there."""
    host, port = split_host_port(address)
    context = ssl.SSLContext(ssl.PROTOCOL_TLS_CLIENT)
    context.check_hostname = False
    context.verify_mode = ssl.CERT_NONE
    context.set_alpn_protocols(["h2"])
    try:
        sock = socket.create_connection((host, port), timeout=timeout)
    except OSError:
        return None
    with sock:
        try:
            with context.wrap_socket(sock, server_hostname=host):
                return True
        except OSError:  # ssl.SSLError included
            return False


def _why_not_grpc(address: str, timeout: float = 2.0) -> str:
    """What listens at ``address`` instead of a gRPC server, for a failed connect's message."""
    port = split_host_port(address)[1]
    start = (
        f"start one with `dinerdash-server --port {port}`, or omit `address` (and "
        "DINERDASH_ADDRESS) to let the client start a local one"
    )
    try:
        with socket.create_connection(split_host_port(address), timeout=timeout) as sock:
            sock.sendall(b"HEAD / HTTP/1.1\r\nHost: localhost\r\nConnection: close\r\n\r\n")
            answer = sock.recv(16)
    except OSError:
        return f"nothing accepts connections there; is it running? {start[0].upper()}{start[1:]}"
    if answer.startswith(b"HTTP/1."):
        return (
            "it answers HTTP/1.1, not gRPC: is this the server's web port (--http-port)? "
            "Clients connect to its gRPC port (--port, 50051 by default)"
        )
    return f"something listens there but did not answer as a gRPC server in time; {start}"


def split_host_port(address: str) -> tuple[str, int]:
    """``"host:port"`` or ``"[v6]:port"`` as ``(host, port)``; no port: :data:`DEFAULT_PORT`."""
    address = address.strip()
    if address.startswith("["):  # [ipv6]:port
        host, _, rest = address[1:].partition("]")
        port = rest.lstrip(":")
        return host, int(port) if port else DEFAULT_PORT
    if address.count(":") == 1:
        host, port = address.split(":")
        return host, int(port)
    return address, DEFAULT_PORT  # a name, or a bare IPv6 literal


def join_host_port(host: str, port: int) -> str:
    """``host:port``, an IPv6 host in brackets."""
    return f"[{host}]:{port}" if ":" in host else f"{host}:{port}"


def parse_addresses(address: str | Sequence[str]) -> list[str]:
    """Normalises an ``address`` argument into a list of ``host:port`` strings."""
    items = address.split(",") if isinstance(address, str) else list(address)
    out = []
    for item in items:
        if not isinstance(item, str) or not item.strip():
            raise ValueError(f"address: expected 'host:port' strings, got {item!r}")
        try:
            host, port = split_host_port(item)
        except ValueError:
            raise ValueError(f"address: bad port in {item!r}; expected 'host:port'") from None
        out.append(join_host_port(host, port))
    if not out:
        raise ValueError("address: no server address given")
    return out


def resolve_replicas(address: str | Sequence[str]) -> list[str]:
    """Every server that ``address`` names, one ``host:port`` per replica."""
    out: list[str] = []
    for item in parse_addresses(address):
        host, port = split_host_port(item)
        try:
            infos = [] if is_ip(host) else socket.getaddrinfo(host, port, type=socket.SOCK_STREAM)
        except OSError:
            infos = []
        v4 = [i[4][0] for i in infos if i[0] == socket.AF_INET]
        ips = list(dict.fromkeys(v4 or [i[4][0] for i in infos if i[0] == socket.AF_INET6]))
        if len(ips) <= 1:
            out.append(item)  # one server: keep the name (nicer in messages, TLS-friendly)
        else:
            out.extend(join_host_port(ip, port) for ip in ips)
    return out


def is_ip(host: str) -> bool:
    """``host`` is an IP address, not a name."""
    try:
        ipaddress.ip_address(host)
    except ValueError:
        return False
    return True


@dataclass(frozen=True)
class ConnectOptions:
    """How to reach the server(s) and what to do when one is lost: one value, built once and
    handed to :func:`gymnasium.make`, :func:`gymnasium.make_vec`, :func:`~dinerdash.rollout` or an
    agent's command as ``connect=`` (docs/client.md#connecting). Every field is also a keyword of
    those, which overrides that field of a ``connect=`` given beside it (:meth:`merged`).

    Attributes:
        address: a ``host:port``, several (a comma-separated string or a list), or a DNS name,
            resolved at each connect; ``None``: ``DINERDASH_ADDRESS``, else a local server.
        token: the auth token (``None``: ``DINERDASH_AUTH_TOKEN``).
        connect_timeout: seconds to wait for a server to answer at first (``None``: 10, or
            ``timeout`` when shorter); a wrong address costs this long.
        timeout: every call's deadline in seconds (:func:`call_timeout`).
        tls, tls_ca: TLS trusting the system's roots, or this PEM CA (``None``:
            ``DINERDASH_TLS_CA``; ``False``: plaintext whatever the environment says).
        server_binary: the local server's binary, when one is started.
        reconnect: when a server is lost, wait for it, open a new session there and report the
            interrupted episodes as truncated, instead of raising.
        reconnect_timeout: seconds a lost server (the last one left, with failover) is waited for.
        failover_after: a vector env over several servers with ``reconnect=True``: seconds a lost
            or silent server is borne with before its environments move to the others; ``None``:
            no failover. The single env ignores it.
        resolve_every: with failover, seconds between resolutions of a DNS-name ``address``,
            whose new replicas are taken in; ``None``: resolved once.
        transport: ``"auto"`` (shared memory when the server is on this machine and runs as
            this user, else gRPC), ``"shm"`` (or an error saying why not) or ``"grpc"``.
    """

    address: str | tuple[str, ...] | None = None
    token: str | None = None
    connect_timeout: float | None = None
    timeout: float | None = None
    tls: bool = False
    tls_ca: str | os.PathLike | bool | None = None
    server_binary: str | os.PathLike | None = None
    reconnect: bool = False
    reconnect_timeout: float = 60.0
    failover_after: float | None = 10.0
    resolve_every: float | None = 30.0
    transport: str = "auto"

    def __post_init__(self) -> None:
        if self.transport not in TRANSPORTS:
            raise ValueError(
                f"transport: expected one of {', '.join(map(repr, TRANSPORTS))}, got "
                f"{self.transport!r}"
            )
        if self.address is not None and not isinstance(self.address, str):
            object.__setattr__(self, "address", tuple(self.address))
        object.__setattr__(self, "timeout", call_timeout(self.timeout))
        if self.connect_timeout is None:
            object.__setattr__(self, "connect_timeout", min(CONNECT_TIMEOUT, self.timeout))
        object.__setattr__(self, "reconnect", bool(self.reconnect))
        for name in ("connect_timeout", "reconnect_timeout"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, numbers.Real) or not value > 0:
                raise ValueError(f"{name}: expected a positive number of seconds, got {value!r}")
        no_failover = "a lost server is waited for reconnect_timeout, as without failover"
        for name, none in (("failover_after", no_failover), ("resolve_every", "never")):
            value = getattr(self, name)
            if value is None:
                continue
            if isinstance(value, bool) or not isinstance(value, numbers.Real):
                raise TypeError(
                    f"{name}: expected a number of seconds or None, got {type(value).__name__} "
                    f"{value!r}"
                )
            if not (value > 0 and math.isfinite(value)):
                raise ValueError(
                    f"{name}: expected a positive, finite number of seconds (or None: {none}), "
                    f"got {value!r}"
                )
            object.__setattr__(self, name, float(value))

    @classmethod
    def merged(cls, connect: ConnectOptions | None, caller: str, **keywords: Any) -> ConnectOptions:
        """``connect`` (``None``: the defaults) with the ``keywords`` given beside it put in (one
        that is no field refused in ``caller``'s name); ``address=None`` keeps its address."""
        unknown = sorted(set(keywords) - set(CONNECT_FIELDS))
        if unknown:
            # Python's own wording ("got an unexpected keyword argument 'x'"), which wrappers
            # match on to drop a keyword they tried (TorchRL's GymEnv tries ``frameskip=``).
            raise TypeError(
                f"{caller}() got an unexpected keyword argument {unknown[0]!r}"
                + (f" (and {', '.join(map(repr, unknown[1:]))})" if unknown[1:] else "")
                + f"; the connection keywords are {', '.join(CONNECT_FIELDS)}"
            )
        if keywords.get("address", 0) is None:
            del keywords["address"]
        if connect is None:
            return cls(**keywords)
        if not isinstance(connect, ConnectOptions):
            raise TypeError(f"connect: expected a ConnectOptions, got {type(connect).__name__}")
        return dataclasses.replace(connect, **keywords) if keywords else connect

    def connect(self, address: str, wait: bool = True) -> Connection:
        """A :class:`Connection` to one server, with these options (``wait=False``: returned at
        once, without waiting for the server to answer)."""
        fields = ("token", "connect_timeout", "timeout", "tls", "tls_ca")
        return Connection(address, wait=wait, **{f: getattr(self, f) for f in fields})


def _pushback_ms(error: grpc.RpcError) -> int | None:
    """The retry push-back's milliseconds a failed call's trailers carry (-1: not a number,
    do not retry), or ``None``."""
    value = trailer(error, RETRY_PUSHBACK)
    try:
        return None if value is None else int(value)
    except (TypeError, ValueError):
        return -1


#: The keywords that :class:`ConnectOptions` stands for, in its field order.
CONNECT_FIELDS = tuple(f.name for f in dataclasses.fields(ConnectOptions))


class Connection:
    """One channel to one server, and the call wrapper that every RPC of the client goes through.

    Args:
        address: ``host:port`` of the server.
        token, connect_timeout, timeout, tls, tls_ca: as :class:`ConnectOptions`'s fields.
        retries: retries of a call that fails with ``UNAVAILABLE`` (docs/client.md#retries).
        retry_backoff: seconds before the first retry (jittered by gRPC); doubled after each one.
        wait: wait (``connect_timeout``) for the server to answer before returning; ``False``
            returns at once (the channel connects at its first call).
    """

    def __init__(
        self,
        address: str,
        *,
        token: str | None = None,
        connect_timeout: float = CONNECT_TIMEOUT,
        retries: int = 4,
        retry_backoff: float = 0.1,
        timeout: float | None = None,
        tls: bool = False,
        tls_ca: str | os.PathLike | bool | None = None,
        wait: bool = True,
    ) -> None:
        self.address = parse_addresses(address)[0]
        if isinstance(retries, bool) or not isinstance(retries, numbers.Integral) or retries < 0:
            raise ValueError(f"retries: expected a whole number >= 0, got {retries!r}")
        if isinstance(retry_backoff, bool) or not isinstance(retry_backoff, numbers.Real):
            raise TypeError(f"retry_backoff: expected seconds, got {retry_backoff!r}")
        if not (retry_backoff >= 0 and math.isfinite(retry_backoff)):
            raise ValueError(f"retry_backoff: expected seconds >= 0, got {retry_backoff!r}")
        self.retries = int(retries)
        self.retry_backoff = float(retry_backoff)
        self.timeout = call_timeout(timeout)
        token = token if token is not None else os.environ.get("DINERDASH_AUTH_TOKEN")
        self._metadata = (("authorization", f"Bearer {token}"),) if token else None
        credentials = tls_credentials(tls, tls_ca)
        self.tls = credentials is not None
        options = [
            *CHANNEL_OPTIONS,
            ("grpc.service_config", service_config(self.retries, self.retry_backoff)),
        ]
        if credentials is None:
            self.channel = grpc.insecure_channel(self.address, options=options)
        else:
            self.channel = grpc.secure_channel(self.address, credentials, options=options)
        self.stub = pb_grpc.DinerDashStub(self.channel)
        self._health: grpc.UnaryUnaryMultiCallable | None = None
        self._closed = False
        if not wait:
            return
        # A short wait, then a TLS probe: a TLS mismatch says so at once, not after the timeout.
        first = min(connect_timeout, 1.0)
        ready = self.wait_ready(first)
        if not ready:
            self._tls_mismatch(final=False)
            ready = self.wait_ready(connect_timeout - first)
        if not ready:
            self._tls_mismatch(final=True)
            self.close()
            raise ServiceTransportError(
                f"could not connect to a dinerdash-server at {self.address} within "
                f"connect_timeout={connect_timeout:g} s: {_why_not_grpc(self.address)}",
                address=self.address,
            )

    def _tls_mismatch(self, final: bool) -> None:
        """Raises :class:`TLSMismatch` (closed) when a failed connect is TLS meeting plaintext,
        or (``final``: after the whole connect timeout) a certificate the client does not trust."""
        speaks_tls = _speaks_tls(self.address)
        if speaks_tls and not self.tls:
            message = (
                f"the server at {self.address} speaks TLS and this client connected in "
                "plaintext; pass tls_ca=PATH (or DINERDASH_TLS_CA) for a private CA or a "
                "self-signed certificate, or tls=True for one signed by a public CA"
            )
        elif speaks_tls is False and self.tls:
            message = (
                f"the server at {self.address} does not speak TLS and this client asked for it "
                "(tls=True, tls_ca or DINERDASH_TLS_CA); connect in plaintext"
            )
        elif speaks_tls and self.tls and final:
            message = (
                f"TLS with the server at {self.address} failed: its certificate is not trusted "
                "(check tls_ca / DINERDASH_TLS_CA) or does not name this host"
            )
        else:
            return
        self.close()
        raise TLSMismatch(message, address=self.address)

    def wait_ready(self, timeout: float) -> bool:
        """Waits up to ``timeout`` seconds for the server to answer; True when it did."""
        try:
            info = self.stub.ServerInfo(
                pb.ServerInfoRequest(),
                timeout=max(timeout, 0.001),
                metadata=self._metadata,
                wait_for_ready=True,
            )
            warn_if_other_version(info.server_version, self.address)
            return True
        except grpc.RpcError as e:
            # Any answer from the server (e.g. UNAUTHENTICATED) means it is there.
            return e.code() not in (grpc.StatusCode.DEADLINE_EXCEEDED, grpc.StatusCode.UNAVAILABLE)

    def call(
        self, method: str, request: Any, *, timeout: float | None = None, retries: int | None = None
    ) -> Any:
        """Calls ``method`` (an RPC name such as ``"Step"``) and returns its reply, or raises its
        typed error; ``UNAVAILABLE`` retried ``retries`` times at most, within ``timeout``."""
        if self._closed:
            self._check_open(method)
        rpc = getattr(self.stub, method)
        timeout = self.timeout if timeout is None else timeout
        try:  # the first attempt inline: a Step's every call
            return rpc(request, timeout=timeout, metadata=self._metadata)
        except grpc.RpcError as e:
            error = e
        again = lambda: rpc(request, timeout=timeout, metadata=self._metadata)  # noqa: E731
        return self._retrying(method, again, error, retries, timeout)

    def future(self, method: str, request: Any) -> grpc.Future:
        """Starts ``method`` without waiting; pass the future to :meth:`result`."""
        self._check_open(method)
        rpc = getattr(self.stub, method)
        return rpc.future(request, timeout=self.timeout, metadata=self._metadata)

    def result(self, method: str, request: Any, future: grpc.Future) -> Any:
        """The reply of a call started by :meth:`future`, with :meth:`call`'s errors and retries."""
        try:
            return future.result()
        except grpc.RpcError as e:
            error = e
        rpc = getattr(self.stub, method)
        again = lambda: rpc(request, timeout=self.timeout, metadata=self._metadata)  # noqa: E731
        return self._retrying(method, again, error)

    def stream(self, method: str, request: Any) -> Iterator[Any]:
        """Iterates the replies of a server-streaming ``method``, with :meth:`call`'s errors; only
        its opening is retried, and it has no deadline (keepalive pings end it)."""
        self._check_open(method)
        rpc = getattr(self.stub, method)

        def open_stream() -> tuple[Iterator[Any], Any]:
            replies = rpc(request, metadata=self._metadata)
            return replies, next(replies, None)

        replies, first = self._retrying(method, open_stream)
        if first is None:
            return
        yield first
        try:
            yield from replies
        except grpc.RpcError as e:
            raise self._error(method, e, 1) from None

    def _check_open(self, method: str) -> None:
        if self._closed:
            raise EnvClosed(
                f"{method}: the connection to {self.address} is closed (the environment was "
                "closed); reset() opens a new session",
                address=self.address,
            )

    def _channel_attempts(self, method: str) -> int:
        """The most attempts the channel makes of one call of ``method`` (its retries + 1)."""
        if method in NOT_RETRIED or method in BY_HAND:
            return 1
        return min(self.retries, CHANNEL_MAX_RETRIES) + 1

    def _retrying(
        self,
        method: str,
        attempt: Callable[[], Any],
        error: grpc.RpcError | None = None,
        retries: int | None = None,
        timeout: float | None = None,
    ) -> Any:
        """The one retry helper beside the channel's (docs/client.md#retries): ``attempt()`` made
        again after ``UNAVAILABLE`` while ``retries`` last, backing off as the channel does,
        unless pushed back; ``error``: the first attempt's, made already."""
        wanted = 0 if method in NOT_RETRIED else self.retries if retries is None else retries
        made = 0
        while True:
            if error is None:
                try:
                    return attempt()
                except grpc.RpcError as e:
                    error = e
            made += self._channel_attempts(method)
            pushback = _pushback_ms(error)
            if (
                error.code() != grpc.StatusCode.UNAVAILABLE
                or made > wanted
                or self._closed
                or (pushback is not None and pushback < 0)
            ):
                raise self._error(method, error, made, timeout) from None
            if pushback is not None:
                time.sleep(pushback / 1000)
            else:
                time.sleep(self.retry_backoff * 2 ** (made - 1))  # doubling on the channel's
            error = None

    def _error(
        self, method: str, error: grpc.RpcError, attempts: int, timeout: float | None = None
    ) -> ServiceError:
        """The typed exception for a failed call (:meth:`error_for`)."""
        status = trailer(error, DETAILS_KEY)
        return self.error_for(
            method, error.code(), error.details(), attempts, timeout, _pushback_ms(error), status
        )

    def error_for(
        self,
        method: str,
        code: grpc.StatusCode,
        details: str,
        attempts: int = 1,
        timeout: float | None = None,
        pushback: int | None = None,
        status: bytes | None = None,
    ) -> ServiceError:
        """The typed exception of ``method``'s failure (``code``, ``details``, ``status``: a
        serialized ``google.rpc.Status``) after ``attempts``, over gRPC and shared memory alike."""
        if code == grpc.StatusCode.UNAVAILABLE:
            made = "1 attempt" if attempts == 1 else f"{attempts} attempts"
            if attempts > 1 and self._channel_attempts(method) > 1:
                made = "up to " + made
            if pushback is not None and pushback < 0:
                made += "; it asked not to be retried"
            details = (
                f"{method}: the server at {self.address} is unavailable after {made} ({details})"
            )
        elif code == grpc.StatusCode.DEADLINE_EXCEEDED:
            timeout = self.timeout if timeout is None else timeout
            return ServiceTimeout(
                f"{method}: no answer from the server at {self.address} within {timeout:g} s "
                "(the timeout= keyword or DINERDASH_TIMEOUT sets this deadline)",
                code=code,
                address=self.address,
            )
        elif code == grpc.StatusCode.CANCELLED and self._closed:
            return EnvClosed(f"{method}: the connection was closed during the call", code=code)
        else:
            details = f"{method}: {details}"
        return error_for_status(code, details or "(no message)", self.address, status)

    def health(self, timeout: float) -> grpc.Future:
        """Starts a ``grpc.health.v1`` Check of the server, sent with the token and waiting for
        the channel (docs/client.md#design-notes); the future's result: SERVING."""
        self._check_open("Check")
        if self._health is None:
            self._health = self.channel.unary_unary(
                "/grpc.health.v1.Health/Check",
                request_serializer=bytes,
                # SERVING (field 1 is 1) read by hand: the client needs no grpcio-health-checking
                response_deserializer=lambda reply: reply == b"\x08\x01",
            )
        return self._health.future(
            b"", timeout=timeout, metadata=self._metadata, wait_for_ready=True
        )

    def server_info(self) -> pb.ServerInfoResponse:
        """The server's version, ruleset and limits."""
        return self.call("ServerInfo", pb.ServerInfoRequest())

    def close(self) -> None:
        """Closes the channel; safe to call twice."""
        if not self._closed:
            self._closed = True
            self.channel.close()

    def __enter__(self) -> Connection:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def __repr__(self) -> str:
        return f"Connection({self.address!r})"

"""The channel to a DinerDash server and the one call wrapper every RPC goes through.

Everything about the network lives here: how to connect (:class:`ConnectOptions`, one value for
every environment, rollout and agent command), the channel options, the address rules (a
``host:port``, a comma-separated or Python list of them, or a DNS name that resolves to several
replicas), the
mapping from gRPC statuses to the typed exceptions of :mod:`dinerdash.errors`, the deadline every
call carries, TLS, and the retry policy: only ``UNAVAILABLE`` is retried, with exponential backoff
and a bounded number of attempts.

Retries are the channel's: its service config (:func:`service_config`) gives every method of
``dinerdash.v1.DinerDash`` a ``retryPolicy`` that retries ``UNAVAILABLE`` ``retries`` times,
backing off ``retry_backoff`` seconds doubled after each retry (gRPC jitters each by up to a
fifth), within the call's one deadline. A draining server's refusal carries the retry push-back
``grpc-retry-pushback-ms: -1``, which tells the channel not to ask it again: the caller gets
:class:`~dinerdash.errors.ServerDraining` at once and goes elsewhere.

What the channel's service config cannot express is done by one fallback, :meth:`Connection._call`:
after the channel has given up on ``UNAVAILABLE`` the call is made again by hand, with the same
backoff and the same push-back rule, until the call's own number of attempts is used up. It covers
exactly these exceptions:

- more than 4 retries: gRPC caps ``maxAttempts`` at 5 attempts (:data:`CHANNEL_MAX_RETRIES`);
- a per-call ``retries=`` above the connection's (grpcio has no per-call retry policy);
- the methods of :data:`BY_HAND`, which the channel does not retry: ``Rollout``, since gRPC commits
  a stream at its response headers (which the server sends before the first episode) and a stream
  broken before its first reply must still be opened again; ``CloseSession``, since closing a
  session at ``close()`` is tried once and briefly (``retries=0``) and only the fallback can make
  a call retry less than the channel.

A per-call ``retries=`` below the connection's, for a method the channel retries, cannot be
expressed either: the channel's count applies. :data:`NOT_RETRIED` (``Step``, ``StepStream``) is
never retried, by the channel or by hand.
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
    EnvClosed,
    ServiceTimeout,
    ServiceTransportError,
    TLSMismatch,
    error_for_rpc,
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

#: Seconds a call may take when neither ``timeout=`` nor ``DINERDASH_TIMEOUT`` says: finite, so
#: that a stuck server becomes an error, and generous enough for a 1024-environment Step or a
#: planner's Step on a loaded 2-core machine.
DEFAULT_TIMEOUT = 60.0
#: Seconds a connection waits for its server to answer at first, unless the call timeout is shorter.
CONNECT_TIMEOUT = 10.0

#: The service whose methods the channel's service config retries.
SERVICE = "dinerdash.v1.DinerDash"

#: Calls never retried on UNAVAILABLE, by the channel or by hand. A Step the server applied but
#: whose reply was lost would be applied twice by a retry, silently changing the episode; it
#: raises instead, and ``reconnect=True`` recovers by reporting the interrupted episode as
#: truncated. A StepStream carries Steps.
NOT_RETRIED = frozenset({"Step", "StepStream"})

#: Calls the channel does not retry but the fallback does (the module's exception list): a
#: Rollout stream broken before its first reply is opened again though gRPC has committed it;
#: CloseSession may be asked for fewer retries than the connection's (none, at ``close()``).
BY_HAND = frozenset({"Rollout", "CloseSession"})

#: The most retries the channel makes of one call: gRPC caps ``retryPolicy.maxAttempts`` at 5.
#: More are made by the fallback.
CHANNEL_MAX_RETRIES = 4

#: The trailer by which a server pushes back on retries (gRFC A6): a negative or unreadable value
#: asks the client not to retry (a draining server's refusal), a positive one to wait that long.
RETRY_PUSHBACK = "grpc-retry-pushback-ms"

CHANNEL_OPTIONS: list[tuple[str, Any]] = [
    # A rollout of one long episode is (T + 1) x (40 + 57) bytes plus per-step fields: allow
    # 256 MiB so that even 100,000-step episodes with action masks arrive in one message.
    ("grpc.max_receive_message_length", 256 * 1024 * 1024),
    # Snapshots of large vector sessions travel client -> server in Restore; the server applies
    # its own (smaller) limit and names it in the INVALID_ARGUMENT it returns.
    ("grpc.max_send_message_length", 256 * 1024 * 1024),
    # Retries by the service config's retryPolicy (service_config, added per connection), and
    # gRPC's transparent retries of calls that never reached the server's application (so never
    # a Step the server applied).
    ("grpc.enable_retries", 1),
    # The retry policy is the client's own (service_config): no DNS TXT record replaces it.
    ("grpc.service_config_disable_resolution", 1),
    # gRPC retries only a request it still holds, 256 KiB by default: hold any request the
    # channel may send (a Restore of a large snapshot), as the requests in flight are held anyway.
    ("grpc.per_rpc_retry_buffer_size", 256 * 1024 * 1024),
    # After a server restart the channel must reconnect within a second or two, not after
    # gRPC's default backoff that grows to two minutes (reconnect=True relies on this).
    ("grpc.initial_reconnect_backoff_ms", 100),
    ("grpc.min_reconnect_backoff_ms", 100),
    ("grpc.max_reconnect_backoff_ms", 2000),
    # Each Connection keeps its own subchannel (TCP connection), so one environment's traffic
    # never queues behind another's and closing one never disturbs the others.
    ("grpc.use_local_subchannel_pool", 1),
    # Environment servers are on loopback or inside the cluster: never send them through an
    # http_proxy that happens to be set for the trainer's downloads.
    ("grpc.enable_http_proxy", 0),
    # Keepalive pings while a call is in flight notice a peer that vanished without closing the
    # connection (a dead host, a dropped route) before the deadline runs out.
    ("grpc.keepalive_time_ms", 20_000),
    ("grpc.keepalive_timeout_ms", 10_000),
    ("grpc.keepalive_permit_without_calls", 0),
    ("grpc.http2.max_pings_without_data", 0),
]


def _duration(seconds: float) -> str:
    """``seconds`` as a protobuf JSON Duration (``"0.100000000s"``), at least a millisecond: gRPC
    wants backoffs above zero."""
    return f"{max(seconds, 0.001):.9f}s"


def service_config(retries: int, retry_backoff: float) -> str:
    """The channel's service config (JSON, the ``grpc.service_config`` channel option): every
    method of :data:`SERVICE` but those of :data:`NOT_RETRIED` and :data:`BY_HAND` retries
    ``UNAVAILABLE`` up to ``min(retries, CHANNEL_MAX_RETRIES)`` times, the first after
    ``retry_backoff`` seconds (gRPC jitters it), each next one after twice the last (up to
    ``2 ** (CHANNEL_MAX_RETRIES - 1)`` times the first: the doubling is never capped within the
    channel's retries). ``retries=0``: no retry policy at all."""
    retries = min(retries, CHANNEL_MAX_RETRIES)
    configs: list[dict[str, Any]] = []
    if retries > 0:
        configs.append(
            {
                "name": [{"service": SERVICE}],
                "retryPolicy": {
                    "maxAttempts": retries + 1,
                    "initialBackoff": _duration(retry_backoff),
                    "maxBackoff": _duration(retry_backoff * 2 ** (CHANNEL_MAX_RETRIES - 1)),
                    "backoffMultiplier": 2,
                    "retryableStatusCodes": ["UNAVAILABLE"],
                },
            }
        )
        # A method's own entry wins over its service's: these have no retry policy.
        configs.append(
            {
                "name": [
                    {"service": SERVICE, "method": method}
                    for method in sorted(NOT_RETRIED | BY_HAND)
                ]
            }
        )
    return json.dumps({"methodConfig": configs}, separators=(",", ":"))


def call_timeout(timeout: float | None) -> float:
    """The deadline of each call, in seconds: ``timeout``, else ``DINERDASH_TIMEOUT``, else
    :data:`DEFAULT_TIMEOUT`. Always finite and positive."""
    if timeout is None:
        text = os.environ.get("DINERDASH_TIMEOUT", "").strip()
        if text:
            try:
                timeout = float(text)
            except ValueError:
                raise ValueError(f"DINERDASH_TIMEOUT: expected seconds, got {text!r}") from None
        else:
            timeout = DEFAULT_TIMEOUT
    timeout = float(timeout)
    if not 0 < timeout < float("inf"):
        raise ValueError(f"timeout: expected a positive number of seconds, got {timeout!r}")
    return timeout


def check_seconds_or_none(name: str, value: Any, none: str = "never") -> float | None:
    """Keyword ``name`` as seconds: ``None``, or a positive finite number (not a bool)."""
    if value is None:
        return None
    if isinstance(value, bool) or not isinstance(value, numbers.Real):
        raise TypeError(
            f"{name}: expected a number of seconds or None, got {type(value).__name__} {value!r}"
        )
    seconds = float(value)
    if not (seconds > 0 and math.isfinite(seconds)):
        raise ValueError(
            f"{name}: expected a positive, finite number of seconds (or None: {none}), "
            f"got {value!r}"
        )
    return seconds


def check_failover_after(failover_after: Any) -> float | None:
    """``failover_after=`` as seconds: ``None``, or a positive finite number (not a bool)."""
    return check_seconds_or_none(
        "failover_after",
        failover_after,
        "a lost server is waited for reconnect_timeout, as without failover",
    )


def tls_credentials(
    tls: bool, tls_ca: str | os.PathLike | bool | None
) -> grpc.ChannelCredentials | None:
    """The channel credentials for ``tls`` / ``tls_ca`` (``None``: ``DINERDASH_TLS_CA``; ``False``:
    no CA and no environment, as for the local server): ``None`` means plaintext; a CA file means
    TLS trusting that CA, ``tls=True`` the system's roots."""
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
    ``None`` when nothing accepts a TCP connection there. Only asked after a failed connect, to
    say why."""
    host, port = split_host_port(address)
    context = ssl.SSLContext(ssl.PROTOCOL_TLS_CLIENT)
    context.check_hostname = False
    context.verify_mode = ssl.CERT_NONE
    context.set_alpn_protocols(["h2"])
    try:
        sock = socket.create_connection((host, port), timeout=timeout)
    except OSError:
        return None
    try:
        with context.wrap_socket(sock, server_hostname=host):
            return True
    except (OSError, ssl.SSLError):
        return False
    finally:
        sock.close()


def _why_not_grpc(address: str, timeout: float = 2.0) -> str:
    """What listens at ``address`` instead of a gRPC server, in words for a failed connect."""
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
    if address.count(":") > 1:  # a bare IPv6 literal
        return address, DEFAULT_PORT
    return address, DEFAULT_PORT


def join_host_port(host: str, port: int) -> str:
    """``host`` and ``port`` as an address, an IPv6 host in brackets."""
    return f"[{host}]:{port}" if ":" in host else f"{host}:{port}"


def parse_addresses(address: str | Sequence[str]) -> list[str]:
    """Normalises an ``address`` argument into a list of ``host:port`` strings.

    ``address`` is a ``host:port``, several separated by commas, or a list of them; a missing port
    means :data:`DEFAULT_PORT`.
    """
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
    """Every server that ``address`` names, one ``host:port`` per replica.

    A DNS name that resolves to several addresses (a Kubernetes headless Service, a round-robin
    record) becomes one entry per address, so that a vector env can give each replica its own
    session. Only addresses of one family are used (IPv4 when there are any), so that ``localhost``
    is one server and not two names for the same one. A name that does not resolve is kept as is:
    connecting to it then fails with a readable error.
    """
    out: list[str] = []
    for item in parse_addresses(address):
        host, port = split_host_port(item)
        try:
            ipaddress.ip_address(host)
            out.append(item)
            continue
        except ValueError:
            pass
        try:
            infos = socket.getaddrinfo(host, port, type=socket.SOCK_STREAM)
        except OSError:
            out.append(item)
            continue
        v4 = [i[4][0] for i in infos if i[0] == socket.AF_INET]
        v6 = [i[4][0] for i in infos if i[0] == socket.AF_INET6]
        ips = list(dict.fromkeys(v4 or v6))
        if len(ips) <= 1:
            out.append(item)  # one server: keep the name (nicer in messages, TLS-friendly)
        else:
            out.extend(join_host_port(ip, port) for ip in ips)
    return out


@dataclass(frozen=True)
class ConnectOptions:
    """How to reach the server(s) and what to do when one is lost: one value, built once and
    handed to :func:`gymnasium.make`, :func:`gymnasium.make_vec`, :func:`~dinerdash.rollout` or
    an agent's command as ``connect=``::

        connect = dinerdash.ConnectOptions(["10.0.0.5:50051", "10.0.0.6:50051"], reconnect=True)
        env = gymnasium.make("dinerdash:DinerDash-v0", connect=connect)
        envs = gymnasium.make_vec("dinerdash:DinerDash-v0", num_envs=64, connect=connect)

    Every field is also a keyword of those functions (``address=``, ``timeout=``, ...): sugar for
    this value, and a keyword given beside ``connect=`` overrides that field of it
    (:meth:`merged`).

    Attributes:
        address: a ``host:port``, several (a comma-separated string or a list, kept as a tuple),
            or a DNS name; ``None``: ``DINERDASH_ADDRESS``, else a local server. It is resolved
            at each connect, so that a DNS name that moved is followed.
        token: the auth token (``None``: ``DINERDASH_AUTH_TOKEN``).
        connect_timeout: seconds to wait for a server to answer at first (``None``: 10, or
            ``timeout`` when that is shorter); a wrong address costs this long.
        timeout: every call's deadline in seconds, resolved here (:func:`call_timeout`).
        tls, tls_ca: TLS trusting the system's roots, or this PEM CA (``None``:
            ``DINERDASH_TLS_CA``; ``False``: plaintext whatever the environment says, as for the
            local server).
        server_binary: the local server's binary, when one is started.
        reconnect: when a server is lost, wait for it (``reconnect_timeout`` seconds), open a new
            session there and report the interrupted episodes as truncated, instead of raising.
        reconnect_timeout: seconds a lost server is waited for (the last one left, for a vector
            env with failover).
        failover_after: a vector env over several servers with ``reconnect=True``: seconds a lost
            server is waited for, or a server that answers nothing at all (a hung process, a
            black-holed network) is borne with, before its environments move to the others;
            ``None``: no failover. The single env has one server and ignores it.
        resolve_every: a vector env with ``reconnect=True`` and failover: seconds between two
            resolutions of a DNS-name ``address``, whose new replicas are taken in; ``None``:
            resolved once, at connect.
        transport: how Steps travel: ``"auto"`` through shared memory when the server is on this
            machine and runs as this user (Linux), else gRPC; ``"shm"`` shared memory or an
            error saying why not; ``"grpc"`` always gRPC (:mod:`dinerdash._shm`).
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
        object.__setattr__(self, "failover_after", check_failover_after(self.failover_after))
        object.__setattr__(
            self, "resolve_every", check_seconds_or_none("resolve_every", self.resolve_every)
        )

    @classmethod
    def merged(cls, connect: ConnectOptions | None, caller: str, **keywords: Any) -> ConnectOptions:
        """``connect`` (``None``: the defaults) with the connection ``keywords`` a function was
        given beside it put in; a keyword that is no field is refused as Python refuses one, in
        ``caller``'s name. ``address=None`` keeps ``connect``'s address."""
        unknown = sorted(set(keywords) - set(CONNECT_FIELDS))
        if unknown:
            # Python's own wording ("got an unexpected keyword argument 'x'"), which wrappers
            # match on to drop a keyword they tried (TorchRL's GymEnv tries ``frameskip=``).
            raise TypeError(
                f"{caller}() got an unexpected keyword argument {unknown[0]!r}"
                + (f" (and {', '.join(map(repr, unknown[1:]))})" if unknown[1:] else "")
                + "; "
                f"the connection keywords are {', '.join(CONNECT_FIELDS)}"
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
        return Connection(
            address,
            token=self.token,
            connect_timeout=self.connect_timeout,
            timeout=self.timeout,
            tls=self.tls,
            tls_ca=self.tls_ca,
            wait=wait,
        )


def _pushback_ms(error: grpc.RpcError) -> int | None:
    """The retry push-back (:data:`RETRY_PUSHBACK`) a failed call's trailers carry: its
    milliseconds, -1 for a value that is not a number (gRFC A6: do not retry), ``None`` when
    there is none."""
    trailers = getattr(error, "trailing_metadata", None)
    for key, value in (trailers() if trailers else None) or ():
        if key == RETRY_PUSHBACK:
            try:
                return int(value)
            except (TypeError, ValueError):
                return -1
    return None


def _serving(reply: bytes) -> bool:
    """A ``grpc.health.v1.HealthCheckResponse`` is SERVING: its field 1 (a varint) is 1. Decoded
    by hand, so that the client needs no grpcio-health-checking."""
    return reply == b"\x08\x01"


#: The keywords that :class:`ConnectOptions` stands for, in its field order.
CONNECT_FIELDS = tuple(f.name for f in dataclasses.fields(ConnectOptions))


class Connection:
    """One channel to one server, and the call wrapper that every RPC of the client goes through.

    Args:
        address: ``host:port`` of the server.
        token: sent as ``authorization: Bearer <token>`` when the server requires one (default:
            the ``DINERDASH_AUTH_TOKEN`` environment variable).
        connect_timeout: seconds to wait for the first connection; past it a readable
            :class:`~dinerdash.errors.ServiceTransportError` says who could not be reached.
        retries: attempts after the first for a call that fails with ``UNAVAILABLE`` (up to 4
            by the channel's service config, more by hand: see the module's exception list).
        retry_backoff: seconds before the first retry (jittered by gRPC); doubled after each one.
        timeout: deadline of each call in seconds (default: ``DINERDASH_TIMEOUT``, else
            :data:`DEFAULT_TIMEOUT`); a call past it raises
            :class:`~dinerdash.errors.ServiceTimeout`.
        tls: connect with TLS, trusting the system's root certificates.
        tls_ca: connect with TLS, trusting this PEM CA certificate (default:
            ``DINERDASH_TLS_CA``); e.g. a self-signed server certificate.
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
        # A first short wait, then the TLS probe, then the rest: a TLS mismatch never gets an
        # answer, and should say so at once rather than after the whole connect timeout.
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
        """Closes the connection and raises :class:`TLSMismatch` when a failed connect is TLS
        meeting plaintext, or (``final``: after the whole connect timeout, since a busy TLS server
        looks the same at first) a certificate the client does not trust."""
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
        """Waits up to ``timeout`` seconds for the server to answer; True when it did.

        A ``ServerInfo`` call with ``wait_for_ready`` rather than ``grpc.channel_ready_future``,
        whose polling thread outlives it and fails noisily when the channel is closed later.
        """
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
        self,
        method: str,
        request: Any,
        *,
        timeout: float | None = None,
        retries: int | None = None,
    ) -> Any:
        """Calls ``method`` (an RPC name such as ``"Step"``) and returns its reply.

        Raises the typed exception for any gRPC error, with the server's message; retries only
        ``UNAVAILABLE``, at most ``retries`` times (default: the connection's) with exponential
        backoff: the channel's retries, and the fallback's beyond them (the module's exception
        list). ``timeout`` is the deadline of the attempts the channel makes together.
        """
        if self._closed:
            self._check_open(method)
        rpc = getattr(self.stub, method)
        timeout = self.timeout if timeout is None else timeout
        # The first attempt inline (a Step's every call: no closure, no loop); the fallback
        # takes over from its error.
        try:
            return rpc(request, timeout=timeout, metadata=self._metadata)
        except grpc.RpcError as e:
            error = e
        return self._call(
            method,
            lambda: rpc(request, timeout=timeout, metadata=self._metadata),
            retries,
            timeout,
            error,
        )

    def future(self, method: str, request: Any) -> grpc.Future:
        """Starts ``method`` without waiting; pass the future to :meth:`result`."""
        self._check_open(method)
        rpc = getattr(self.stub, method)
        return rpc.future(request, timeout=self.timeout, metadata=self._metadata)

    def result(self, method: str, request: Any, future: grpc.Future) -> Any:
        """The reply of a call started by :meth:`future`, with the same errors and retries as
        :meth:`call` (the future's attempts were the channel's; the fallback calls again)."""
        try:
            return future.result()
        except grpc.RpcError as e:
            error = e
        rpc = getattr(self.stub, method)
        return self._call(
            method,
            lambda: rpc(request, timeout=self.timeout, metadata=self._metadata),
            None,
            None,
            error,
        )

    def stream(self, method: str, request: Any) -> Iterator[Any]:
        """Iterates the replies of a server-streaming ``method``, mapping errors as :meth:`call`
        does. Only the opening of the stream is retried (before its first reply, by the
        fallback: ``Rollout`` is in :data:`BY_HAND`): a stream broken half-way raises.

        A stream has no overall deadline (a long rollout may rightly take many minutes): the
        keepalive pings, which a stopped or vanished server cannot answer, end it instead."""
        self._check_open(method)
        rpc = getattr(self.stub, method)
        wanted = self._wanted(method, None)
        made = 0
        while True:
            received = False
            try:
                for reply in rpc(request, metadata=self._metadata):
                    received = True
                    yield reply
                return
            except grpc.RpcError as e:
                error = e
            made += 1 if received else self._channel_attempts(method)
            delay = None if received else self._fallback_delay(error, made, wanted)
            if delay is None:
                raise self._error(method, error, made) from None
            time.sleep(delay)

    def _check_open(self, method: str) -> None:
        if self._closed:
            raise EnvClosed(
                f"{method}: the connection to {self.address} is closed (the environment was "
                "closed); reset() opens a new session",
                address=self.address,
            )

    def _wanted(self, method: str, retries: int | None) -> int:
        """The retries a call of ``method`` may make: ``retries``, else the connection's; none
        for :data:`NOT_RETRIED`."""
        if method in NOT_RETRIED:
            return 0
        return self.retries if retries is None else retries

    def _channel_attempts(self, method: str) -> int:
        """The most attempts the channel makes of one call of ``method`` (its retries + 1)."""
        if method in NOT_RETRIED or method in BY_HAND:
            return 1
        return min(self.retries, CHANNEL_MAX_RETRIES) + 1

    def _call(
        self,
        method: str,
        attempt: Callable[[], Any],
        retries: int | None,
        timeout: float | None,
        error: grpc.RpcError | None = None,
    ) -> Any:
        """``attempt()`` (one call through the channel, which retries by its service config),
        made again by the fallback while the call's retries are not used up; ``error``: the
        first attempt was made already, and failed so."""
        wanted = self._wanted(method, retries)
        made = 0
        while True:
            if error is None:
                try:
                    return attempt()
                except grpc.RpcError as e:
                    error = e
            made += self._channel_attempts(method)
            delay = self._fallback_delay(error, made, wanted)
            if delay is None:
                raise self._error(method, error, made, timeout) from None
            time.sleep(delay)
            error = None

    def _fallback_delay(self, error: grpc.RpcError, made: int, wanted: int) -> float | None:
        """Seconds before the fallback calls again after ``error``, with ``made`` attempts made
        (at most) and ``wanted`` retries allowed; ``None``: raise. Only ``UNAVAILABLE`` is
        retried, and, as the channel does, never after a push-back that says not to (a draining
        server's refusal); a push-back of N ms waits N ms. The backoff goes on doubling from the
        channel's last."""
        if error.code() != grpc.StatusCode.UNAVAILABLE or made > wanted or self._closed:
            return None
        pushback = _pushback_ms(error)
        if pushback is not None:
            return None if pushback < 0 else pushback / 1000
        return self.retry_backoff * 2 ** (made - 1)

    def _error(
        self, method: str, error: grpc.RpcError, attempts: int, timeout: float | None = None
    ):
        """The typed exception for ``error``, after at most ``attempts`` attempts (exactly that
        many when the channel does not retry ``method``; the channel does not say how many it
        made)."""
        code, details = error.code(), error.details()
        if code == grpc.StatusCode.UNAVAILABLE:
            if attempts == 1:
                made = "1 attempt"
            elif self._channel_attempts(method) == 1:
                made = f"{attempts} attempts"
            else:
                made = f"up to {attempts} attempts"
            pushback = _pushback_ms(error)
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
        return error_for_rpc(error, details, self.address)

    def health(self, timeout: float) -> grpc.Future:
        """Starts a ``grpc.health.v1`` Check of the whole server (answered even while it drains;
        sent with the auth token, which a server with a probe port asks for) on this channel;
        the future's result is True when the server is SERVING, False when it answered
        otherwise. A server that answers nothing leaves the future pending until ``timeout``.
        What a vector env's watch and membership probe ask.

        The check waits for the channel to connect (``wait_for_ready``) instead of failing at
        once while the channel backs off after a lost connection: so a server that came back is
        found by the next check, whose wait is what drives the reconnection. (Over shared memory
        no other call may be polling gRPC: failing fast, a returning server went unfound for
        1-14 s.)"""
        self._check_open("Check")
        if self._health is None:
            self._health = self.channel.unary_unary(
                "/grpc.health.v1.Health/Check",
                request_serializer=bytes,
                response_deserializer=_serving,
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

"""The exceptions of the client.

Every gRPC status the server returns becomes one of these, carrying the server's own message (which
names the offending field and its allowed range)::

    ServiceError                      any failure of a call to the server
    ├── SessionNotFound               NOT_FOUND: unknown, closed or expired session
    ├── InvalidArgument (ValueError)  INVALID_ARGUMENT: a bad action, seed, arrival list, config ...
    ├── FailedPrecondition            FAILED_PRECONDITION: e.g. stepping an episode that is over
    ├── ResourceExhausted             RESOURCE_EXHAUSTED: too many sessions, message too large
    ├── Unauthenticated               UNAUTHENTICATED: missing or wrong auth token
    ├── ServiceTimeout (TimeoutError) DEADLINE_EXCEEDED
    ├── ServiceInternalError          INTERNAL, UNKNOWN and any other code
    └── ServiceTransportError (OSError)  UNAVAILABLE after the retries, or no connection

``LocalServerError`` is about starting a local ``dinerdash-server``; ``ServerBinaryNotFound`` (also
a ``FileNotFoundError``) says how to build one or point to one.
"""

from __future__ import annotations

import grpc

__all__ = [
    "FailedPrecondition",
    "InvalidArgument",
    "LocalServerError",
    "ResourceExhausted",
    "ServerBinaryNotFound",
    "ServiceError",
    "ServiceInternalError",
    "ServiceTimeout",
    "ServiceTransportError",
    "SessionNotFound",
    "Unauthenticated",
    "error_for_status",
]


class ServiceError(Exception):
    """A call to the DinerDash server failed.

    Attributes:
        code: the gRPC status code, or ``None`` when the failure happened before any call.
        details: the server's message.
        address: the ``host:port`` of the server that was called.
    """

    def __init__(
        self,
        details: str,
        *,
        code: grpc.StatusCode | None = None,
        address: str | None = None,
    ) -> None:
        self.code = code
        self.details = details
        self.address = address
        where = f" ({address})" if address else ""
        name = f"{code.name}: " if code is not None else ""
        super().__init__(f"{name}{details}{where}")


class SessionNotFound(ServiceError):
    """The session is unknown to the server: closed, expired, or the server was restarted."""


class InvalidArgument(ServiceError, ValueError):
    """The server refused an argument; the message names the field and its allowed range."""


class FailedPrecondition(ServiceError):
    """The call does not fit the session's state (e.g. an episode that is over; call reset)."""


class ResourceExhausted(ServiceError):
    """A server limit was reached (sessions, message size)."""


class Unauthenticated(ServiceError):
    """The server wants ``authorization: Bearer <token>`` and the token was missing or wrong."""


class ServiceTimeout(ServiceError, TimeoutError):
    """A call ran past its deadline."""


class ServiceInternalError(ServiceError):
    """The server failed in a way the contract does not name (INTERNAL, UNKNOWN, ...)."""


class ServiceTransportError(ServiceError, OSError):
    """The server could not be reached: refused, lost, or still down after the retries."""


class LocalServerError(RuntimeError):
    """A local ``dinerdash-server`` could not be started."""


class ServerBinaryNotFound(LocalServerError, FileNotFoundError):
    """No ``dinerdash-server`` binary was found to start a local server."""


_BY_CODE: dict[grpc.StatusCode, type[ServiceError]] = {
    grpc.StatusCode.NOT_FOUND: SessionNotFound,
    grpc.StatusCode.INVALID_ARGUMENT: InvalidArgument,
    grpc.StatusCode.OUT_OF_RANGE: InvalidArgument,
    grpc.StatusCode.FAILED_PRECONDITION: FailedPrecondition,
    grpc.StatusCode.RESOURCE_EXHAUSTED: ResourceExhausted,
    grpc.StatusCode.UNAUTHENTICATED: Unauthenticated,
    grpc.StatusCode.PERMISSION_DENIED: Unauthenticated,
    grpc.StatusCode.DEADLINE_EXCEEDED: ServiceTimeout,
    grpc.StatusCode.UNAVAILABLE: ServiceTransportError,
}


def error_for_status(
    code: grpc.StatusCode, details: str, address: str | None = None
) -> ServiceError:
    """The typed exception for a gRPC status."""
    cls = _BY_CODE.get(code, ServiceInternalError)
    return cls(details or "(no message)", code=code, address=address)

"""The exceptions of the client (the table: docs/client.md#errors). Every gRPC status becomes one
of these, with the server's message; the class, ``reason``, ``field`` and ``env_index`` come from
the status code and its structured details (``ErrorInfo``, ``BadRequest``), never from the text.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import grpc

__all__ = [
    "EnvClosed",
    "EpisodeOver",
    "FailedPrecondition",
    "InvalidArgument",
    "LocalServerError",
    "NoServerLeft",
    "ResourceExhausted",
    "ServerBinaryNotFound",
    "ServerDraining",
    "ServiceError",
    "ServiceInternalError",
    "ServiceTimeout",
    "ServiceTransportError",
    "SessionNotFound",
    "TLSMismatch",
    "Unauthenticated",
    "error_for_status",
]

#: The ``ErrorInfo.domain`` of the DinerDash service's errors.
ERROR_DOMAIN = "dinerdash.v1"
#: The trailer that carries a serialized ``google.rpc.Status`` (the gRPC rich error model).
DETAILS_KEY = "grpc-status-details-bin"


class ServiceError(Exception):
    """A call to the DinerDash server failed.

    Attributes:
        code: the gRPC status code, or ``None`` when the failure happened before any call.
        details: the server's message; ``address``: the server called.
        reason: the server's stable reason code (``ErrorInfo.reason``), e.g. ``"EPISODE_OVER"``.
        field: the offending request field (``BadRequest``), e.g. ``"actions[3]"``.
        env_index: the environment concerned (a vector env's index); ``metadata``: the rest.
    """

    def __init__(
        self,
        details: str,
        *,
        code: grpc.StatusCode | None = None,
        address: str | None = None,
        reason: str | None = None,
        field: str | None = None,
        env_index: int | None = None,
        metadata: Mapping[str, str] | None = None,
    ) -> None:
        self.code = code
        self.details = details
        self.address = address
        self.reason = reason
        self.field = field
        self.env_index = env_index
        self.metadata = dict(metadata or {})
        where = f" ({address})" if address else ""
        name = f"{code.name}: " if code is not None else ""
        super().__init__(f"{name}{details}{where}")


class SessionNotFound(ServiceError):
    """The session is unknown to the server: closed, expired, or the server was restarted."""


class InvalidArgument(ServiceError, ValueError):
    """The server refused an argument; the message names the field and its allowed range."""


class FailedPrecondition(ServiceError):
    """The call does not fit the session's state (e.g. an episode that is over; call reset)."""


class EpisodeOver(FailedPrecondition):
    """An autoreset-DISABLED environment (``env_index``) was stepped after its episode ended."""


class ResourceExhausted(ServiceError):
    """A server limit was reached (sessions, message size)."""


class Unauthenticated(ServiceError):
    """The server wants ``authorization: Bearer <token>`` and the token was missing or wrong.
    Its message says how this client sends one: ``token=`` or ``DINERDASH_AUTH_TOKEN``."""

    def __init__(self, details: str, **kwargs: Any) -> None:
        super().__init__(details, **kwargs)
        self.args = (f"{self.args[0]}; this client sends token= or DINERDASH_AUTH_TOKEN",)


class ServiceTimeout(ServiceError, TimeoutError):
    """A call ran past its deadline."""


class ServiceInternalError(ServiceError):
    """The server failed in a way the contract does not name (INTERNAL, UNKNOWN, ...)."""


class ServiceTransportError(ServiceError, OSError):
    """The server could not be reached: refused, lost, or still down after the retries."""


class ServerDraining(ServiceTransportError):
    """The server is draining before a planned restart (it got SIGTERM): it serves the sessions it
    has until its drain timeout, but starts no new one; CreateSession, Fork, Restore and Rollout are
    refused with ``UNAVAILABLE`` and reason ``DRAINING``."""

    @property
    def drain_remaining_ms(self) -> int | None:
        """Milliseconds left before the server ends the sessions it still serves."""
        value = self.metadata.get("drain_remaining_ms", "")
        return int(value) if value.isdigit() else None


class TLSMismatch(ServiceTransportError):
    """The client and the server disagree about TLS: pass ``tls=True`` or ``tls_ca=PATH`` (or
    ``DINERDASH_TLS_CA``) for a server started with ``--tls-cert``, and neither for a plaintext
    one."""


class NoServerLeft(ServiceTransportError):
    """Every server of a vector env spread over several was lost (``reconnect=True``,
    ``failover_after``): the last did not come back within ``reconnect_timeout``, or the last ones
    were lost together."""


class EnvClosed(ServiceError):
    """The environment was closed; ``reset()`` opens a new session."""


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


#: Reasons with a more precise class than their status code's.
_BY_REASON: dict[str, type[ServiceError]] = {
    "EPISODE_OVER": EpisodeOver,
    "DRAINING": ServerDraining,
}


def error_for_status(
    code: grpc.StatusCode,
    details: str,
    address: str | None = None,
    status_details: bytes | None = None,
) -> ServiceError:
    """The typed exception for a gRPC status and its ``grpc-status-details-bin`` trailer (a
    serialized ``google.rpc.Status``: ``reason``, ``field``, ``env_index``, other metadata)."""
    reason = field = env_index = None
    metadata: dict[str, str] = {}
    if status_details:
        # Imported on first use: only failing calls pay for the google.rpc descriptors.
        from google.rpc import error_details_pb2, status_pb2

        status = status_pb2.Status()
        try:
            status.ParseFromString(status_details)
        except Exception:  # a trailer we cannot read is no worse than none
            status = status_pb2.Status()
        for detail in status.details:
            if detail.Is(error_details_pb2.ErrorInfo.DESCRIPTOR):
                info = error_details_pb2.ErrorInfo()
                detail.Unpack(info)
                if info.domain == ERROR_DOMAIN:
                    reason = info.reason
                    metadata.update(info.metadata)
            elif detail.Is(error_details_pb2.BadRequest.DESCRIPTOR):
                bad = error_details_pb2.BadRequest()
                detail.Unpack(bad)
                if bad.field_violations:
                    field = bad.field_violations[0].field
        index = metadata.pop("env_index", None)
        env_index = int(index) if index is not None and index.isdigit() else None
    cls = _BY_REASON.get(reason or "") or _BY_CODE.get(code, ServiceInternalError)
    return cls(
        details or "(no message)",
        code=code,
        address=address,
        reason=reason,
        field=field,
        env_index=env_index,
        metadata=metadata,
    )


def trailer(error: grpc.RpcError, key: str) -> Any:
    """A failed call's trailer ``key`` (e.g. :data:`DETAILS_KEY`), or ``None``."""
    trailers = getattr(error, "trailing_metadata", None)
    for name, value in (trailers() if trailers else None) or ():
        if name == key:
            return value
    return None

"""Pieces shared by the single and the vector environment: checking and turning Python arguments
(render mode, reset options, config, arrivals) into protocol messages, choosing and connecting to
the server(s) (:class:`Endpoint`: address, deadline, TLS, the local server), and building the
spaces from a session's Spec. The session itself is :mod:`dinerdash._core`'s."""

from __future__ import annotations

import os
import time
from collections.abc import Callable, Mapping, Sequence
from typing import Any

import numpy as np
from gymnasium import spaces

from ._proto import pb
from .connection import Connection, resolve_replicas
from .errors import ServiceError, ServiceTransportError
from .server import LocalServer

#: Observation length and number of actions (docs/rules.md sections 6 and 4.1).
OBSERVATION_SIZE = 40
NUM_ACTIONS = 57

#: The fields of GameConfig, i.e. the keys a ``config`` mapping may hold.
CONFIG_FIELDS = tuple(f.name for f in pb.GameConfig.DESCRIPTOR.fields)

Config = Mapping[str, int] | pb.GameConfig | None
Arrivals = Sequence[tuple[int, int]] | Sequence[Mapping[str, int]]


#: The ``expert=`` values that name a server-side expert, and the policy the server plays for them.
EXPERTS = {"expert": pb.POLICY_EXPERT, "planner": pb.POLICY_PLANNER}


def expert_fields(expert: bool | str) -> dict[str, Any]:
    """The CreateSession fields for ``expert=``: ``False`` (no ``expert_action``), ``True`` or
    ``"expert"`` (the reference heuristic), or ``"planner"`` (the look-ahead planner)."""
    if isinstance(expert, str):
        if expert not in EXPERTS:
            raise ValueError(f"expert must be a bool or one of {sorted(EXPERTS)}, got {expert!r}")
        return {"expert_actions": True, "expert_policy": EXPERTS[expert]}
    return {"expert_actions": bool(expert), "expert_policy": pb.POLICY_EXPERT}


def make_config(config: Config) -> pb.GameConfig | None:
    """A GameConfig from a mapping such as ``{"lives": 3, "time_limit": 1000}``."""
    if config is None or isinstance(config, pb.GameConfig):
        return config
    if not isinstance(config, Mapping):
        raise TypeError(
            f"config: expected a mapping of {CONFIG_FIELDS}, got {type(config).__name__}"
        )
    unknown = sorted(set(config) - set(CONFIG_FIELDS))
    if unknown:
        raise ValueError(
            f"config: unknown field(s) {unknown}; the fields are {list(CONFIG_FIELDS)}"
        )
    msg = pb.GameConfig()
    for key, value in config.items():
        if value is not None:
            if int(value) < 0:
                raise ValueError(f"config: {key} must be a non-negative integer, got {value!r}")
            setattr(msg, key, int(value))
    return msg


def config_dict(config: pb.GameConfig) -> dict[str, int]:
    """The fields present in a GameConfig, as a plain dict."""
    return {
        f.name: getattr(config, f.name) for f in config.DESCRIPTOR.fields if config.HasField(f.name)
    }


def _arrival(group: Any) -> pb.Arrival:
    if isinstance(group, Mapping):
        return pb.Arrival(customer_type=int(group["customer_type"]), size=int(group["size"]))
    customer_type, size = group
    return pb.Arrival(customer_type=int(customer_type), size=int(size))


def _is_arrival_list(value: Any) -> bool:
    """True for one list of groups (its first entry a (type, size) pair or a mapping)."""
    if len(value) == 0:
        return True
    first = value[0]
    if isinstance(first, Mapping):
        return True
    return len(first) == 2 and all(np.ndim(x) == 0 for x in first)


def make_arrivals(arrivals: Any, num_envs: int = 1) -> list[pb.ArrivalList]:
    """ArrivalLists from one list of ``(customer_type, size)`` pairs (every environment gets it)
    or, for a vector env, a list of such lists (one per environment)."""
    if arrivals is None:
        return []
    if _is_arrival_list(arrivals):
        return [pb.ArrivalList(groups=[_arrival(g) for g in arrivals])]
    lists = [pb.ArrivalList(groups=[_arrival(g) for g in one]) for one in arrivals]
    if num_envs == 1 and len(lists) != 1:
        raise ValueError("arrivals: give one list of (customer_type, size) pairs")
    return lists


RENDER_MODES = ("ansi", "rgb_array")


def check_render_mode(render_mode: str | None) -> str | None:
    """``render_mode`` if it is one of :data:`RENDER_MODES` or ``None``; else ValueError."""
    if render_mode is not None and render_mode not in RENDER_MODES:
        raise ValueError(
            f"render_mode must be None or one of {list(RENDER_MODES)}, got {render_mode!r}"
        )
    return render_mode


def check_options(options: Mapping[str, Any] | None, known: Sequence[str]) -> dict[str, Any]:
    """The reset ``options`` as a dict, refusing keys outside ``known``."""
    options = dict(options or {})
    unknown = sorted(set(options) - set(known))
    if unknown:
        raise ValueError(
            f"reset options: unknown key(s) {unknown}; known: {', '.join(map(repr, known))}"
        )
    return options


def close_session(conn: Connection, session_id: str) -> None:
    """Closes a session, once and briefly: a server that is gone or already forgot the session
    has nothing left to free."""
    try:
        request = pb.CloseSessionRequest(session_id=session_id)
        conn.call("CloseSession", request, timeout=2.0, retries=0)
    except ServiceError:
        pass


def observation_space(spec: pb.Spec) -> spaces.Box:
    """The Box of docs/rules.md section 6, with the bounds the server reports."""
    if spec.observation_size != OBSERVATION_SIZE or spec.num_actions != NUM_ACTIONS:
        raise RuntimeError(
            f"the server reports {spec.observation_size} observations and {spec.num_actions} "
            f"actions; this client knows {OBSERVATION_SIZE} and {NUM_ACTIONS} (ruleset v0)"
        )
    low = np.asarray(spec.observation_low, dtype=np.float32)
    high = np.asarray(spec.observation_high, dtype=np.float32)
    return spaces.Box(low=low, high=high, dtype=np.float32)


def choose_addresses(address: str | Sequence[str] | None) -> list[str] | None:
    """The replicas to use: from ``address``, else ``DINERDASH_ADDRESS``; ``None`` means "start a
    local server"."""
    if address is None:
        address = os.environ.get("DINERDASH_ADDRESS") or None
    if address is None:
        return None
    return resolve_replicas(address)


class Endpoint:
    """Connections to one or more servers, and the local server this client started, if any.

    Every connection gets the same deadline (``timeout``) and TLS settings (``tls``, ``tls_ca``);
    a local server is plaintext on loopback. Closing it closes every channel and stops the local
    server.
    """

    def __init__(
        self,
        address: str | Sequence[str] | None,
        *,
        max_servers: int | None = None,
        token: str | None = None,
        connect_timeout: float = 10.0,
        server_binary: str | None = None,
        pick: int | None = None,
        timeout: float | None = None,
        tls: bool = False,
        tls_ca: str | os.PathLike | None = None,
    ) -> None:
        self.token = token
        self.connect_timeout = connect_timeout
        self.timeout = timeout
        self.tls = tls
        self.tls_ca = tls_ca
        self.server: LocalServer | None = None
        self.connections: list[Connection] = []
        addresses = choose_addresses(address)
        if addresses is None:
            # The local server is plaintext on loopback: TLS settings are for remote servers.
            self.tls, self.tls_ca = False, None
            self.server = LocalServer(server_binary)
            addresses = [self.server.address]
        if pick is not None:
            addresses = [addresses[pick % len(addresses)]]
        if max_servers is not None:
            addresses = addresses[:max_servers]
        self.addresses = addresses
        try:
            for a in addresses:
                self.connections.append(self.connect(a))
        except BaseException:
            self.close()
            raise

    def connect(self, address: str, connect_timeout: float | None = None) -> Connection:
        timeout = self.connect_timeout if connect_timeout is None else connect_timeout
        return Connection(
            address,
            token=self.token,
            connect_timeout=timeout,
            timeout=self.timeout,
            tls=self.tls,
            tls_ca=self.tls_ca,
        )

    def reopen(
        self, index: int, create: Callable[[Connection], None], lost: str, timeout: float
    ) -> Connection:
        """Waits up to ``timeout`` seconds for server ``index`` to answer again, then calls
        ``create`` with its connection to open a new session there (``reconnect=True``).

        A local server this client owns that died is started again (on a new free port). Returns
        the connection to use from now on; ``lost`` names what was lost, for the error raised
        when the server does not come back in time.
        """
        deadline = time.monotonic() + timeout
        while True:
            # Checked on every round: a dying process may still look alive at first.
            if self.server is not None and not self.server.is_running():
                self.server.start()
                self.connections[index].close()
                self.connections[index] = self.connect(self.server.address)
            conn = self.connections[index]
            if conn.wait_ready(min(1.0, max(0.0, deadline - time.monotonic()))):
                try:
                    create(conn)
                    return conn
                except ServiceTransportError:
                    pass  # went away again between connecting and creating: keep waiting
            if time.monotonic() >= deadline:
                raise ServiceTransportError(
                    f"lost {lost} and could not reconnect to {conn.address} within {timeout:g} s",
                    address=conn.address,
                ) from None
            time.sleep(0.1)

    def close(self) -> None:
        for conn in self.connections:
            conn.close()
        self.connections = []
        if self.server is not None:
            self.server.stop()
            self.server = None


class SessionOwner:
    """What :class:`~dinerdash.DinerDashEnv` and :class:`~dinerdash.DinerDashVectorEnv` share:
    the :class:`Endpoint` they opened and the server's ``Spec`` of their session."""

    _endpoint: Endpoint
    spec_proto: pb.Spec

    @property
    def server(self):
        """The :class:`~dinerdash.server.LocalServer` this env started, or ``None``."""
        return self._endpoint.server

    @property
    def game_config(self) -> dict[str, int]:
        """The effective game configuration, every field present."""
        return config_dict(self.spec_proto.config)

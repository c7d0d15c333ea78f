"""The Diner Dash Gymnasium environment, played on a DinerDash server."""

from __future__ import annotations

import copy
import random
import struct
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any, ClassVar, SupportsFloat

import gymnasium as gym
import numpy as np
from gymnasium import spaces

from . import render as _render
from ._proto import pb
from ._session import (
    NUM_ACTIONS,
    Config,
    Endpoint,
    SessionOwner,
    close_session,
    expert_fields,
    make_arrivals,
    make_config,
)
from ._session import observation_space as _observation_space
from .connection import Connection
from .errors import InvalidArgument, ServiceError, ServiceTransportError, SessionNotFound

__all__ = ["DinerDashEnv", "Snapshot"]

# The 57 valid actions as the 4 little-endian bytes the server expects, built once.
_ACTION_BYTES = tuple(struct.pack("<i", a) for a in range(NUM_ACTIONS))


@dataclass(frozen=True)
class Snapshot:
    """A saved environment: the server's snapshot bytes and the observation and info of the state
    they hold (the server's bytes alone do not say what the agent saw).

    ``data`` restores on this or any server of the same snapshot version.
    """

    data: bytes
    observation: np.ndarray
    info: dict[str, Any] = field(default_factory=dict)

    def __bytes__(self) -> bytes:
        return self.data


class DinerDashEnv(SessionOwner, gym.Env[np.ndarray, np.int64]):
    """
    ## Description

    Diner Dash, the restaurant game of the DinerDash Gym benchmark (Chen, Ma, Hsu), ruleset
    ``v0``: the waitress seats arriving groups at six tables, takes their orders to the kitchen,
    brings the food, collects the bill and clears the dishes, before the groups lose patience.
    The game runs on a ``dinerdash-server``; this class is a thin client of one server session.
    The rules, bit for bit those of the reference simulator, are in docs/rules.md.

    ## Action Space

    ``Discrete(57)``:

    | action  | meaning |
    |---------|---------|
    | 0       | wait |
    | 1..6    | go to table ``a`` (take the order, serve its food, collect the bill or the dishes) |
    | 7       | hand the orders in hand to the kitchen |
    | 8..13   | pick up the food of table ``a - 7`` from a counter |
    | 14      | drop the dishes in hand at the wash point |
    | 15..56  | seat waiting group ``(a - 15) // 6 + 1`` at table ``(a - 15) % 6 + 1`` |

    An action whose preconditions do not hold changes nothing but lets time pass;
    ``info["action_mask"]`` says which actions have an effect.

    ## Observation Space

    ``Box(40,)`` of ``float32`` with tight bounds per index (integers on the wire):

    | index            | observation                                           | min | max |
    |------------------|-------------------------------------------------------|-----|-----|
    | ``3(t-1)``       | status of table ``t`` (0 free .. 6 waiting for bill)  | 0   | 6   |
    | ``3(t-1) + 1``   | capacity of table ``t``                               | 0   | 6   |
    | ``3(t-1) + 2``   | patience level ``P // 200`` of its group, -1 if none  | -1  | 4   |
    | ``18 + (t-1)``   | 1 if table ``t``'s food is on a counter               | 0   | 1   |
    | ``24 + 2(g-1)``  | patience level of waiting group ``g`` (0 if none)     | 0   | 4   |
    | ``25 + 2(g-1)``  | size of waiting group ``g`` (0 if none)               | 0   | 6   |
    | ``38``, ``39``   | hand slots: 0, ``t`` order, ``6+t`` food, ``12+t`` dish | 0 | 18  |

    ## Rewards

    The change of the game score over the step: +10 to +50 for each service action, -500 for a
    group that runs away from its table (a group that leaves the queue costs a life, no score).

    ## Starting State

    Empty tables, an empty counter and empty hands; the arrival list of 200 groups is drawn from
    the seed (MT19937, as CPython's ``random.seed(seed)`` in the reference) and the first group
    arrives at once. ``reset(options={"arrivals": [(type, size), ...]})`` gives the list instead.

    ## Episode End

    * Termination: the configured number of groups (5) have been lost.
    * Truncation: the configured ``time_limit`` was reached (none by default, as in the
      reference); or, with ``reconnect=True``, the server was lost and the session recreated.

    ## Information

    ``reset`` and ``step`` return ``info`` with ``action_mask`` (``bool`` array of 57), ``score``
    (the episode's total so far), ``lost`` (groups lost), ``tick`` (ticks since reset), and with
    ``expert=True`` ``expert_action``, the reference expert's choice in the state returned. The
    ``reset`` info also holds ``seed``, the seed that replays the episode.

    ## Arguments

    ```python
    env = gymnasium.make("dinerdash:DinerDash-v0", address="localhost:50051", expert=True)
    ```

    * ``address``: ``"host:port"`` of a server (a list or a DNS name with several addresses:
      one of them is chosen at random). Default: ``DINERDASH_ADDRESS``, else a local server is
      started on a free port and stopped by ``close()``.
    * ``expert``: add ``expert_action`` to every info: ``True`` the reference heuristic's choice,
      ``"planner"`` the look-ahead planner's (0.1-0.2 ms a step more on the server).
    * ``reconnect``: when the server is lost (unreachable after the retries, or restarted and no
      longer knowing the session), wait up to ``reconnect_timeout`` seconds for it, recreate the
      session and report the interrupted episode as truncated instead of raising.
    * ``config``: game configuration, e.g. ``{"lives": 3, "time_limit": 2000}`` (the GameConfig
      fields of the protocol; absent fields keep the ``v0`` rules).
    * ``render_mode``: ``"ansi"`` (the server's text board) or ``"rgb_array"`` (a picture).
    * ``token``: auth token (default ``DINERDASH_AUTH_TOKEN``); ``connect_timeout``,
      ``reconnect_timeout`` in seconds; ``server_binary`` for the local server; ``ansi_color``.

    Reset options: ``{"arrivals": [(customer_type, size), ...], "config": {...}}``.

    Extras: :meth:`fork`, :meth:`snapshot` / :meth:`restore`.

    ## Version History

    * v0: ruleset ``v0`` of the DinerDash Gym benchmark, served over gRPC.
    """

    metadata: ClassVar[dict[str, Any]] = {"render_modes": ["ansi", "rgb_array"], "render_fps": 8}

    def __init__(
        self,
        address: str | Sequence[str] | None = None,
        *,
        expert: bool | str = False,
        reconnect: bool = False,
        config: Config = None,
        render_mode: str | None = None,
        token: str | None = None,
        connect_timeout: float = 10.0,
        reconnect_timeout: float = 60.0,
        server_binary: str | None = None,
        ansi_color: bool = False,
    ) -> None:
        if render_mode is not None and render_mode not in self.metadata["render_modes"]:
            raise ValueError(
                f"render_mode must be one of {self.metadata['render_modes']}, got {render_mode!r}"
            )
        self.render_mode = render_mode
        self._expert_fields = expert_fields(expert)
        self.expert = self._expert_fields["expert_actions"]
        self.reconnect = bool(reconnect)
        self.reconnect_timeout = reconnect_timeout
        self.ansi_color = ansi_color
        self._config = make_config(config)
        self._session_id: str | None = None
        self._last_obs: np.ndarray | None = None
        self._last_info: dict[str, Any] = {}
        # A list or a many-address DNS name: one replica at random, so that many single envs
        # (e.g. under AsyncVectorEnv) spread over the replicas.
        self._endpoint = Endpoint(
            address,
            token=token,
            connect_timeout=connect_timeout,
            server_binary=server_binary,
            pick=random.randrange(1 << 30),
        )
        self._conn: Connection = self._endpoint.connections[0]
        try:
            self._create_session()
        except BaseException:
            self._endpoint.close()
            raise
        self.observation_space = _observation_space(self.spec_proto)
        self.action_space = spaces.Discrete(self.spec_proto.num_actions)

    # -- session --------------------------------------------------------------------------------

    @property
    def address(self) -> str:
        """``host:port`` of the server that holds this environment's session."""
        return self._conn.address

    @property
    def session_id(self) -> str | None:
        """The server's id of this environment's session."""
        return self._session_id

    def _create_session(self) -> None:
        request = pb.CreateSessionRequest(
            num_envs=1,
            config=self._config,
            autoreset_mode=pb.AUTORESET_MODE_DISABLED,
            action_masks=True,
            **self._expert_fields,
        )
        reply = self._conn.call("CreateSession", request)
        self._session_id = reply.session_id
        self.spec_proto: pb.Spec = reply.spec

    def _recover(self, error: ServiceError) -> None:
        """Waits for the server to come back and opens a new session there (reconnect=True)."""

        def create(conn: Connection) -> None:
            self._conn = conn
            self._create_session()

        self._endpoint.reopen(0, create, f"the session ({error})", self.reconnect_timeout)

    # -- Gymnasium API ------------------------------------------------------------------------

    def reset(
        self, *, seed: int | None = None, options: dict[str, Any] | None = None
    ) -> tuple[np.ndarray, dict[str, Any]]:
        super().reset(seed=seed)
        options = options or {}
        unknown = sorted(set(options) - {"arrivals", "config"})
        if unknown:
            raise ValueError(
                f"reset options: unknown key(s) {unknown}; known: 'arrivals', 'config'"
            )
        arrivals = make_arrivals(options.get("arrivals"))
        config = make_config(options.get("config"))
        if config is not None:
            self._config = config  # also the configuration of a session recreated later

        def request() -> pb.ResetRequest:
            r = pb.ResetRequest(session_id=self._session_id, arrivals=arrivals, config=config)
            if seed is not None:
                r.seed = seed
            return r

        try:
            batch = self._conn.call("Reset", request())
        except (ServiceTransportError, SessionNotFound) as e:
            if not self.reconnect:
                raise
            self._recover(e)
            batch = self._conn.call("Reset", request())
        obs, info = self._decode(batch)
        info["seed"] = batch.seeds[0]
        self._last_obs, self._last_info = obs, info
        return obs.copy(), dict(info)

    def step(self, action: Any) -> tuple[np.ndarray, SupportsFloat, bool, bool, dict[str, Any]]:
        a = int(action)
        if 0 <= a < NUM_ACTIONS:
            data = _ACTION_BYTES[a]
        else:
            try:
                data = struct.pack("<i", a)  # the server refuses it with INVALID_ARGUMENT
            except struct.error:
                raise InvalidArgument(f"action: {a} is out of 0..=56") from None
        try:
            batch = self._conn.call(
                "Step", pb.StepRequest(session_id=self._session_id, actions=data)
            )
        except (ServiceTransportError, SessionNotFound) as e:
            if not self.reconnect or self._last_obs is None:
                raise
            self._recover(e)
            info = copy.deepcopy(self._last_info)
            info["reconnected"] = True
            return self._last_obs.copy(), 0.0, False, True, info
        obs, info = self._decode(batch)
        self._last_obs, self._last_info = obs, info
        reward = float(int.from_bytes(batch.rewards, "little", signed=True))
        return obs.copy(), reward, batch.terminated[0] != 0, batch.truncated[0] != 0, dict(info)

    def _decode(self, batch: pb.Batch) -> tuple[np.ndarray, dict[str, Any]]:
        obs = np.frombuffer(batch.observations, dtype=np.int8).astype(np.float32)
        info: dict[str, Any] = {
            "action_mask": np.frombuffer(batch.action_masks, dtype=np.bool_).copy(),
            "score": int.from_bytes(batch.scores, "little", signed=True),
            "lost": int.from_bytes(batch.lost, "little"),
            "tick": int.from_bytes(batch.ticks, "little"),
        }
        if self.expert:
            info["expert_action"] = batch.expert_actions[0]
        return obs, info

    def render(self) -> str | np.ndarray | None:
        if self.render_mode is None:
            gym.logger.warn(
                "render() called without a render_mode; pass render_mode='ansi' or 'rgb_array'"
            )
            return None
        if self.render_mode == "ansi":
            request = pb.RenderRequest(
                session_id=self._session_id, env_index=0, color=self.ansi_color
            )
            return self._conn.call("Render", request).text
        if self._last_obs is None:
            raise gym.error.ResetNeeded("call reset() before render()")
        return _render.draw(
            self._last_obs,
            score=self._last_info["score"],
            lost=self._last_info["lost"],
            lives=self.spec_proto.config.lives,
        )

    def close(self) -> None:
        if self._session_id is not None:
            close_session(self._conn, self._session_id)
            self._session_id = None
        self._endpoint.close()
        super().close()

    # -- extras from the server ---------------------------------------------------------------

    def fork(self) -> DinerDashEnv:
        """A new environment in exactly this one's state (game, random stream), on the same
        server, with its own session. Close it when done; it lives on the server this env uses
        (if this env started a local server, closing this env stops it)."""
        reply = self._conn.call("Fork", pb.ForkRequest(session_id=self._session_id))
        child = copy.copy(self)
        child._endpoint = Endpoint(
            self._conn.address,
            token=self._endpoint.token,
            connect_timeout=self._endpoint.connect_timeout,
        )
        child._conn = child._endpoint.connections[0]
        child._session_id = reply.session_id
        child.spec_proto = reply.spec
        child._last_obs = None if self._last_obs is None else self._last_obs.copy()
        child._last_info = copy.deepcopy(self._last_info)
        child._np_random = copy.deepcopy(self._np_random)
        return child

    def snapshot(self) -> Snapshot:
        """Saves the session (game state and random stream); see :meth:`restore`."""
        reply = self._conn.call("Snapshot", pb.SnapshotRequest(session_id=self._session_id))
        obs = (
            np.zeros(self.observation_space.shape, np.float32)
            if self._last_obs is None
            else self._last_obs.copy()
        )
        return Snapshot(reply.snapshot, obs, copy.deepcopy(self._last_info))

    def restore(self, snapshot: Snapshot) -> tuple[np.ndarray, dict[str, Any]]:
        """Replaces this environment's session by one restored from ``snapshot`` (made by this
        env or any other, on any server of the same snapshot version) and returns the observation
        and info of the restored state."""
        reply = self._conn.call("Restore", pb.RestoreRequest(snapshot=bytes(snapshot)))
        old = self._session_id
        self._session_id, self.spec_proto = reply.session_id, reply.spec
        if old is not None:
            try:
                self._conn.call("CloseSession", pb.CloseSessionRequest(session_id=old))
            except SessionNotFound:
                pass
        self._last_obs = snapshot.observation.copy()
        self._last_info = copy.deepcopy(snapshot.info)
        return self._last_obs.copy(), copy.deepcopy(self._last_info)

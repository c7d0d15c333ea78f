"""The Diner Dash Gymnasium environment, played on a DinerDash server."""

from __future__ import annotations

import copy
import dataclasses
import random
import struct
import weakref
from collections.abc import Sequence
from typing import Any, ClassVar, SupportsFloat

import gymnasium as gym
import numpy as np
from gymnasium import spaces
from gymnasium.vector import AutoresetMode

from ._arguments import RENDER_MODES, Config, check_options, make_arrivals, make_config
from ._batch import decode_one, outcome_one
from ._endpoint import Endpoint
from ._proto import pb
from ._session import SessionCore, SessionOwner, check_actions, close_session
from .connection import ConnectOptions
from .errors import InvalidArgument
from .game import NUM_ACTIONS, observation_space

__all__ = ["DinerDashEnv", "Snapshot"]

# The 57 valid actions as the 4 little-endian bytes the server expects, built once.
_ACTION_BYTES = tuple(struct.pack("<i", a) for a in range(NUM_ACTIONS))


def _close(core: SessionCore, endpoint: Endpoint) -> None:
    core.close()
    endpoint.close()


@dataclasses.dataclass(frozen=True)
class Snapshot:
    """A saved environment: the server's snapshot bytes (``data``: restored on any server of the
    same snapshot version) and the observation and info of the state they hold."""

    data: bytes
    observation: np.ndarray
    info: dict[str, Any] = dataclasses.field(default_factory=dict)

    def __bytes__(self) -> bytes:
        return self.data


class DinerDashEnv(SessionOwner, gym.Env[np.ndarray, np.int64]):
    """Diner Dash, ruleset ``v0`` of the DinerDash Gym benchmark (Chen, Ma, Hsu), one game in one
    session of a ``dinerdash-server``: a thin client. Actions ``Discrete(57)``, observations
    ``Box(40,)`` of ``float32``, rewards the change of the score; the rules, bit for bit the
    reference's, are in docs/rules.md; keywords, infos and errors in docs/client.md.

    ```python
    env = gymnasium.make("dinerdash:DinerDash-v0", address="localhost:50051", expert=True)
    ```

    Arguments: ``address`` (default ``DINERDASH_ADDRESS``, else a local server started here and
    stopped by ``close()``; several: one at random), ``expert`` (``True``: the reference
    heuristic's ``expert_action``, ``"planner"``: the look-ahead planner's), ``config`` (GameConfig
    fields, e.g. ``{"lives": 3}``), ``render_mode`` (``"ansi"`` or ``"rgb_array"``),
    ``ansi_color``, ``connect`` (a :class:`~dinerdash.ConnectOptions`) and its fields as keywords
    (``timeout``, ``reconnect``, ``tls_ca``, ``token``, ...), each overriding ``connect``'s.
    Reset options: ``arrivals``, ``config``. Extras: :meth:`action_masks`, :meth:`fork`,
    :meth:`snapshot` / :meth:`restore`, :meth:`watch_url`.
    """

    metadata: ClassVar[dict[str, Any]] = {"render_modes": list(RENDER_MODES), "render_fps": 8}

    def __init__(
        self,
        address: str | Sequence[str] | None = None,
        *,
        expert: bool | str = False,
        config: Config = None,
        render_mode: str | None = None,
        ansi_color: bool = False,
        connect: ConnectOptions | None = None,
        **connection: Any,
    ) -> None:
        self._settings = self._take_arguments(
            1, AutoresetMode.DISABLED, address, expert, render_mode, ansi_color, connect, connection
        )
        self._settings.config = make_config(config)
        self._last_obs: np.ndarray | None = None
        self._last_info: dict[str, Any] = {}
        self._open()
        self.observation_space = observation_space(self.spec_proto)
        self.action_space = spaces.Discrete(self.spec_proto.num_actions)

    def _open(self) -> None:
        """Connects and creates the session (at construction, and at a reset after close), on
        one replica at random: many single envs (e.g. under AsyncVectorEnv) spread over them."""
        self._endpoint = Endpoint(self._options, pick=random.randrange(1 << 30))
        self._core = SessionCore(self._endpoint, 0, 0, 1, self._settings)
        try:
            self.spec_proto: pb.Spec = self._core.create()
        except BaseException:
            self._endpoint.close()
            raise
        # Run by close(), or at exit for an env never closed (its session would wait out the TTL).
        self._finalizer = weakref.finalize(self, _close, self._core, self._endpoint)
        self._closed = False

    @property
    def address(self) -> str:
        """``host:port`` of the server that holds this environment's session."""
        return self._core.conn.address

    @property
    def session_id(self) -> str | None:
        """The server's id of this environment's session."""
        return self._core.session_id

    @property
    def _cores(self) -> list[SessionCore]:
        return [self._core]

    def _shown(self) -> tuple[Any, Any, Any]:
        if self._last_obs is None:
            raise gym.error.ResetNeeded("call reset() before render()")
        return [self._last_obs], [self._last_info["score"]], [self._last_info["lost"]]

    def reset(
        self, *, seed: int | None = None, options: dict[str, Any] | None = None
    ) -> tuple[np.ndarray, dict[str, Any]]:
        super().reset(seed=seed)
        options = check_options(options, ("arrivals", "config"))
        arrivals = make_arrivals(options.get("arrivals"))
        config = make_config(options.get("config"))
        if config is not None:
            self._settings.config = config  # also the configuration of a session recreated later
        if self._closed:
            self._open()  # reuse after close: a new session (and a new local server if needed)
        request = self._core.reset_request(seed=seed, arrivals=arrivals, config=config)
        batch = self._core.reset(request)
        obs, info = decode_one(batch, self.expert)
        info["seed"] = int(batch["seeds"][0])
        self._last_obs, self._last_info = obs, info
        return obs.copy(), dict(info)

    def step(self, action: Any) -> tuple[np.ndarray, SupportsFloat, bool, bool, dict[str, Any]]:
        if isinstance(action, (int, np.integer)):
            a = int(action)
        else:  # one integer as an array (np.array(3), [3]); floats and strings refused, as Discrete
            acts = np.asarray(action)
            if acts.size != 1 or acts.dtype.kind not in "iu":
                raise InvalidArgument(
                    f"action must be an integer in 0..={NUM_ACTIONS - 1}, got {action!r}",
                    reason="ACTION_NOT_INTEGER",
                    field="action",
                )
            a = int(acts.reshape(()))
        if 0 <= a < NUM_ACTIONS:
            data = _ACTION_BYTES[a]
        else:
            data = check_actions([a], 1).tobytes()  # raises, as for a vector env
        self._check_open("step()")
        batch = self._core.step(data)
        if self._core.take_reconnected():
            info = copy.deepcopy(self._last_info)
            info["reconnected"] = True
            return self._last_obs.copy(), 0.0, False, True, info
        obs, info = decode_one(batch, self.expert)
        info["seed"] = self._last_info["seed"]  # every step's info has reset's keys
        self._last_obs, self._last_info = obs, info
        reward, terminated, truncated = outcome_one(batch)
        return obs.copy(), reward, terminated, truncated, dict(info)

    def action_masks(self) -> np.ndarray:
        """The 57 actions that have an effect in the current state, as a ``bool`` array: what
        sb3-contrib's MaskablePPO asks for (``info["action_mask"]`` holds the same)."""
        self._check_open("action_masks()")
        if self._last_obs is None:
            raise gym.error.ResetNeeded("call reset() before action_masks()")
        return self._last_info["action_mask"].copy()

    def close(self) -> None:
        """Closes the session (and a local server this env started); a later ``reset()`` opens
        a new one, other calls raise :class:`~dinerdash.EnvClosed`."""
        if not self._closed:
            self._finalizer()
            self._closed = True
        super().close()

    def fork(self) -> DinerDashEnv:
        """A new environment in exactly this one's state (game, random stream), with its own
        session on the same server (a local server this env started stops with this env)."""
        self._check_open("fork()")
        reply = self._core.conn.call("Fork", pb.ForkRequest(session_id=self.session_id))
        child = copy.copy(self)
        child._options = dataclasses.replace(
            self._options, address=self.address, server_binary=None
        )
        child._endpoint = Endpoint(child._options)
        child._core = SessionCore(child._endpoint, 0, 0, 1, copy.copy(self._settings))
        child._settings = child._core.settings
        child._core.adopt(reply)
        child._finalizer = weakref.finalize(child, _close, child._core, child._endpoint)
        child.spec_proto = reply.spec
        child._last_obs = None if self._last_obs is None else self._last_obs.copy()
        child._last_info = copy.deepcopy(self._last_info)
        child._np_random = copy.deepcopy(self._np_random)
        return child

    def snapshot(self) -> Snapshot:
        """Saves the session (game state and random stream); see :meth:`restore`."""
        self._check_open("snapshot()")
        reply = self._core.conn.call("Snapshot", pb.SnapshotRequest(session_id=self.session_id))
        obs = self._last_obs
        obs = np.zeros(self.observation_space.shape, np.float32) if obs is None else obs.copy()
        return Snapshot(reply.snapshot, obs, copy.deepcopy(self._last_info))

    def restore(self, snapshot: Snapshot) -> tuple[np.ndarray, dict[str, Any]]:
        """Replaces this environment's session by one restored from ``snapshot`` (of any env, on
        any server of the same snapshot version); returns its observation and info."""
        self._check_open("restore()")
        reply = self._core.conn.call("Restore", pb.RestoreRequest(snapshot=bytes(snapshot)))
        old = self.session_id
        self._core.adopt(reply)
        self.spec_proto = reply.spec
        if old is not None:
            close_session(self._core.conn, old)
        self._last_obs = snapshot.observation.copy()
        self._last_info = copy.deepcopy(snapshot.info)
        return self._last_obs.copy(), copy.deepcopy(self._last_info)

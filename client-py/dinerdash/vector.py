"""The vector environment: N Diner Dash games in one batched server session per server.

``gymnasium.make_vec("dinerdash:DinerDash-v0", num_envs=N, ...)`` builds this class (the
registered ``vector_entry_point``). Each step is one ``Step`` call per server carrying N actions as
packed little-endian ``int32``; the reply's packed arrays are turned into numpy arrays with
``numpy.frombuffer``, with no Python loop over the environments.

Scale-out: ``address`` may be a list of servers (or a DNS name that resolves to several). The N
environments are then split into contiguous slices, one batched session per server, and the
servers are called concurrently (gRPC futures). Environment ``i`` is seeded with ``seed + i``
whatever server holds it, so the trajectories are the same as on one server. A session's calls
always go to the server that created it.
"""

from __future__ import annotations

import re
from collections.abc import Sequence
from typing import Any

import gymnasium as gym
import numpy as np
from gymnasium import spaces
from gymnasium.vector import AutoresetMode, VectorEnv
from gymnasium.vector.utils import batch_space

from . import render as _render
from ._proto import pb
from ._session import (
    NUM_ACTIONS,
    OBSERVATION_SIZE,
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

__all__ = ["DinerDashVectorEnv"]

_WIRE_AUTORESET = {
    AutoresetMode.NEXT_STEP: pb.AUTORESET_MODE_NEXT_STEP,
    AutoresetMode.SAME_STEP: pb.AUTORESET_MODE_SAME_STEP,
    AutoresetMode.DISABLED: pb.AUTORESET_MODE_DISABLED,
}
_U64 = 1 << 64
#: How a server's message names one of its session's environments.
_ENV_INDEX = re.compile(r"\benvironment (\d+)\b")


class _Shard:
    """The environments ``start:stop`` of the vector env, in one session on one server."""

    __slots__ = ("conn", "last", "pending", "session_id", "start", "stop")

    def __init__(self, conn: Connection, start: int, stop: int) -> None:
        self.conn = conn
        self.start = start
        self.stop = stop
        #: The session on ``conn``'s server.
        self.session_id: str | None = None
        #: The last Batch received, kept for render() and for reporting a lost server.
        self.last: pb.Batch | None = None
        #: NEXT_STEP after a reconnect: the new session's first Batch, to hand out at the next
        #: step() as that step's autoreset (Gymnasium's NEXT_STEP semantics).
        self.pending: pb.Batch | None = None

    @property
    def size(self) -> int:
        return self.stop - self.start


class DinerDashVectorEnv(SessionOwner, VectorEnv):
    """``num_envs`` Diner Dash environments stepped together on one or more DinerDash servers.

    The single environment, its spaces and infos are described in
    :class:`dinerdash.env.DinerDashEnv`; here every value gains a leading axis of ``num_envs``:
    observations ``(N, 40) float32``, rewards ``(N,) float64``, ``info["action_mask"]`` ``(N, 57)
    bool``, ``info["score"]``, ``info["lost"]``, ``info["tick"]`` and (``expert=True``)
    ``info["expert_action"]`` of shape ``(N,)``, each with its Gymnasium ``_key`` mask.

    Autoreset: ``AutoresetMode.NEXT_STEP`` (default; the step after an episode ends resets that
    environment, ignores its action and reports reward 0 and ``info["seed"]``) or
    ``AutoresetMode.SAME_STEP`` (the ending step returns the new episode's first observation and
    puts the ended one's last observation in ``info["final_obs"]`` and its infos in
    ``info["final_info"]``) or ``AutoresetMode.DISABLED`` (stepping a finished environment raises
    :class:`~dinerdash.errors.FailedPrecondition`; reset it with ``options={"reset_mask": ...}``).
    ``metadata["autoreset_mode"]`` says which.

    Args:
        num_envs: number of environments N.
        address: a server, a list of servers, or a DNS name resolving to several; with several,
            the environments are split into contiguous slices, one per server (at most N servers).
            Default: ``DINERDASH_ADDRESS``, else a local server is started and stopped on close.
        expert: add ``expert_action`` to the infos: ``True`` the reference heuristic's choices,
            ``"planner"`` the look-ahead planner's.
        reconnect: when a server is lost, wait for it (``reconnect_timeout`` seconds), recreate
            its session and report its environments' episodes as truncated.
        autoreset_mode: ``AutoresetMode.NEXT_STEP``, ``SAME_STEP`` or ``DISABLED``.
        config: game configuration (GameConfig fields), as for the single env.
        max_episode_steps: shorthand for ``config["time_limit"]`` (the server truncates).
        render_mode: ``"ansi"`` or ``"rgb_array"``; ``render()`` returns one frame per env.
        token, connect_timeout, reconnect_timeout, server_binary, ansi_color: as for the single env.

    Reset: ``reset(seed=s)`` seeds environment ``i`` with ``s + i``; ``seed`` may also be a list
    of N seeds. Options: ``{"arrivals": one list of (type, size) pairs or N lists,
    "config": {...}, "reset_mask": (N,) bool array}``. With a ``reset_mask`` (any autoreset mode,
    as in Gymnasium) only those environments are reset, environment ``i`` still with ``s + i``;
    the others keep their episode, and the observations and infos returned are their current ones
    (``info["_seed"]`` is the mask of environments reset). A ``config`` needs a full reset.
    """

    def __init__(
        self,
        num_envs: int = 1,
        address: str | Sequence[str] | None = None,
        *,
        expert: bool | str = False,
        reconnect: bool = False,
        autoreset_mode: AutoresetMode | str = AutoresetMode.NEXT_STEP,
        config: Config = None,
        max_episode_steps: int | None = None,
        render_mode: str | None = None,
        token: str | None = None,
        connect_timeout: float = 10.0,
        reconnect_timeout: float = 60.0,
        server_binary: str | None = None,
        ansi_color: bool = False,
    ) -> None:
        mode = AutoresetMode(autoreset_mode)
        if render_mode not in (None, "ansi", "rgb_array"):
            raise ValueError(
                f"render_mode must be None, 'ansi' or 'rgb_array', got {render_mode!r}"
            )
        self.metadata = {
            "render_modes": ["ansi", "rgb_array"],
            "render_fps": 8,
            "autoreset_mode": mode,
        }
        self.autoreset_mode = mode
        self.render_mode = render_mode
        self.num_envs = int(num_envs)
        self._expert_fields = expert_fields(expert)
        self.expert = self._expert_fields["expert_actions"]
        self.reconnect = bool(reconnect)
        self.reconnect_timeout = reconnect_timeout
        self.ansi_color = ansi_color
        self._config = make_config(config)
        #: Shards whose server was lost and reconnected during the current step.
        self._reconnected: list[_Shard] = []
        if max_episode_steps is not None:
            cfg = pb.GameConfig()
            if self._config is not None:
                cfg.CopyFrom(self._config)
            cfg.time_limit = int(max_episode_steps)
            self._config = cfg
        self._endpoint = Endpoint(
            address,
            max_servers=max(1, self.num_envs),
            token=token,
            connect_timeout=connect_timeout,
            server_binary=server_binary,
        )
        conns = self._endpoint.connections
        k = len(conns)
        sizes = [self.num_envs // k + (j < self.num_envs % k) for j in range(k)]
        self._shards: list[_Shard] = []
        start = 0
        for conn, size in zip(conns, sizes, strict=True):
            self._shards.append(_Shard(conn, start, start + size))
            start += size
        try:
            for shard in self._shards:
                self._create_session(shard)
        except BaseException:
            self._close_sessions()
            self._endpoint.close()
            raise
        spec = self.spec_proto
        self.single_observation_space = _observation_space(spec)
        self.single_action_space = spaces.Discrete(spec.num_actions)
        self.observation_space = batch_space(self.single_observation_space, self.num_envs)
        self.action_space = batch_space(self.single_action_space, self.num_envs)

    # -- sessions -------------------------------------------------------------------------------

    @property
    def addresses(self) -> list[str]:
        """The servers, in the order of the environment slices they hold."""
        return [s.conn.address for s in self._shards]

    @property
    def env_slices(self) -> list[tuple[str, slice]]:
        """Which server holds which environments."""
        return [(s.conn.address, slice(s.start, s.stop)) for s in self._shards]

    @property
    def session_ids(self) -> list[str | None]:
        return [s.session_id for s in self._shards]

    def _create_session(self, shard: _Shard) -> None:
        request = pb.CreateSessionRequest(
            num_envs=shard.size,
            config=self._config,
            autoreset_mode=_WIRE_AUTORESET[self.autoreset_mode],
            action_masks=True,
            **self._expert_fields,
        )
        reply = shard.conn.call("CreateSession", request)
        shard.session_id = reply.session_id
        shard.last = None
        shard.pending = None
        self.spec_proto: pb.Spec = reply.spec

    def _reopen(self, shard: _Shard, error: ServiceError) -> None:
        """Waits for a lost server and opens a new session there (reconnect=True)."""

        def create(conn: Connection) -> None:
            shard.conn = conn
            self._create_session(shard)

        lost = f"environments {shard.start}..{shard.stop - 1} ({error})"
        self._endpoint.reopen(self._shards.index(shard), create, lost, self.reconnect_timeout)

    def _fail(self, shard: _Shard, error: ServiceError) -> ServiceError:
        """The same error, saying which environments it concerns when there are several servers
        (an environment the server names by its index in the shard gets its index here)."""
        if len(self._shards) == 1:
            return error
        details = _ENV_INDEX.sub(
            lambda m: f"environment {shard.start + int(m.group(1))}", error.details, count=1
        )
        return type(error)(
            f"{details} [environments {shard.start}..{shard.stop - 1} of the vector env]",
            code=error.code,
            address=error.address,
        )

    # -- Gymnasium API --------------------------------------------------------------------------

    def reset(
        self,
        *,
        seed: int | Sequence[int] | None = None,
        options: dict[str, Any] | None = None,
    ) -> tuple[np.ndarray, dict[str, Any]]:
        seeds = None
        if seed is None or isinstance(seed, (int, np.integer)):
            super().reset(seed=None if seed is None else int(seed))
        else:
            seeds = [int(s) for s in seed]
            if len(seeds) != self.num_envs:
                raise ValueError(
                    f"seed: expected an int or {self.num_envs} seeds, got {len(seeds)}"
                )
        options = dict(options or {})
        unknown = sorted(set(options) - {"arrivals", "config", "reset_mask"})
        if unknown:
            raise ValueError(
                f"reset options: unknown key(s) {unknown}; known: 'arrivals', 'config', "
                "'reset_mask'"
            )
        mask = self._reset_mask(options.get("reset_mask"), options.get("config"))
        arrivals = make_arrivals(options.get("arrivals"), self.num_envs)
        if len(self._shards) > 1 and len(arrivals) not in (0, 1, self.num_envs):
            raise InvalidArgument(
                f"arrivals: expected one list or {self.num_envs} lists (one per environment), "
                f"got {len(arrivals)}"
            )
        config = make_config(options.get("config"))
        if config is not None:
            self._config = config

        def request(shard: _Shard, partial: bool = True) -> pb.ResetRequest:
            r = pb.ResetRequest(session_id=shard.session_id, config=config)
            if mask is not None and partial:
                r.reset_mask = mask[shard.start : shard.stop].astype(np.uint8).tobytes()
            if seeds is not None:
                r.seeds.extend(seeds[shard.start : shard.stop])
            elif seed is not None:
                r.seed = (int(seed) + shard.start) % _U64
            if len(arrivals) == 1 or len(self._shards) == 1:
                r.arrivals.extend(arrivals)
            elif arrivals:
                r.arrivals.extend(arrivals[shard.start : shard.stop])
            return r

        # A shard with none of its environments in the mask is not called: it keeps its state.
        requests = [
            request(s) if mask is None or mask[s.start : s.stop].any() else None
            for s in self._shards
        ]
        futures = [
            s.conn.future("Reset", r) if r is not None else None
            for s, r in zip(self._shards, requests, strict=True)
        ]
        batches, reset = [], []
        for shard, req, fut in zip(self._shards, requests, futures, strict=True):
            if req is None:
                batches.append(shard.last)
                reset.append(bytes(shard.size))
                continue
            try:
                batch = shard.conn.result("Reset", req, fut)
            except (ServiceTransportError, SessionNotFound) as e:
                if not self.reconnect:
                    raise self._fail(shard, e) from None
                self._reopen(shard, e)
                # The new session starts every environment of the shard afresh.
                batch = shard.conn.call("Reset", request(shard, partial=False))
            except ServiceError as e:
                raise self._fail(shard, e) from None
            shard.last, shard.pending = batch, None
            batches.append(batch)
            reset.append(batch.reset)
        obs, info = self._decode_common(batches)
        info["seed"] = self._seeds(batches)
        info["_seed"] = np.frombuffer(b"".join(reset), dtype=np.bool_).copy()
        return obs, info

    def _reset_mask(self, reset_mask: Any, config: Any) -> np.ndarray | None:
        """The ``reset_mask`` option checked as Gymnasium's vector envs check it, or ``None``."""
        if reset_mask is None:
            return None
        if not isinstance(reset_mask, np.ndarray):
            raise TypeError(
                f"options['reset_mask'] must be a numpy array, got {type(reset_mask).__name__}"
            )
        if reset_mask.shape != (self.num_envs,) or reset_mask.dtype != np.bool_:
            raise ValueError(
                f"options['reset_mask'] must be a bool array of shape ({self.num_envs},), got "
                f"{reset_mask.dtype} {reset_mask.shape}"
            )
        if not reset_mask.any():
            raise ValueError("options['reset_mask'] selects no environment")
        if config is not None:
            raise ValueError(
                "options['config'] applies to every environment: give it with a full reset, "
                "not a reset_mask"
            )
        for shard in self._shards:
            if shard.last is None and not reset_mask[shard.start : shard.stop].all():
                kept = shard.start + int(np.flatnonzero(~reset_mask[shard.start : shard.stop])[0])
                raise ValueError(
                    f"environment {kept} has never been reset: include it in reset_mask"
                )
        return reset_mask

    def step(
        self, actions: Any
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, dict[str, Any]]:
        acts = np.asarray(actions)
        if acts.shape != (self.num_envs,):
            raise ValueError(f"actions: expected shape ({self.num_envs},), got {acts.shape}")
        # Checked here, before any server steps: int32 casting would wrap large values into range,
        # and over several servers a step refused by one would have moved the others.
        bad = np.flatnonzero((acts < 0) | (acts >= NUM_ACTIONS))
        if bad.size:
            i = int(bad[0])
            raise InvalidArgument(f"actions[{i}] must be in 0..={NUM_ACTIONS - 1}, got {acts[i]}")
        wire = acts.astype("<i4", copy=False)
        shards = self._shards
        if len(shards) == 1 and shards[0].pending is None:
            shard = shards[0]
            try:
                batch = shard.conn.call(
                    "Step", pb.StepRequest(session_id=shard.session_id, actions=wire.tobytes())
                )
            except (ServiceTransportError, SessionNotFound) as e:
                batch = self._recover_step(shard, e)
            shard.last = batch
            return self._decode_step([batch])
        calls = []
        for shard in shards:
            if shard.pending is not None:
                calls.append((None, None))
                continue
            req = pb.StepRequest(
                session_id=shard.session_id, actions=wire[shard.start : shard.stop].tobytes()
            )
            calls.append((req, shard.conn.future("Step", req)))
        batches = []
        for shard, (req, fut) in zip(shards, calls, strict=True):
            if fut is None:
                batch, shard.pending = shard.pending, None
            else:
                try:
                    batch = shard.conn.result("Step", req, fut)
                except (ServiceTransportError, SessionNotFound) as e:
                    batch = self._recover_step(shard, e)
                except ServiceError as e:
                    raise self._fail(shard, e) from None
            shard.last = batch
            batches.append(batch)
        return self._decode_step(batches)

    def _recover_step(self, shard: _Shard, error: ServiceError) -> pb.Batch:
        """A Batch that reports the shard's interrupted episodes as truncated, after opening a
        new session for them (reconnect=True); raises ``error`` otherwise."""
        if not self.reconnect or shard.last is None:
            raise self._fail(shard, error) from None
        last = shard.last
        self._reopen(shard, error)
        first = shard.conn.call("Reset", pb.ResetRequest(session_id=shard.session_id))
        n = shard.size
        out = pb.Batch()
        if self.autoreset_mode != AutoresetMode.SAME_STEP:
            # This step ends the episodes (last state, truncated). NEXT_STEP: the next step()
            # hands out the new session's first observations as the autoreset. DISABLED: the
            # caller resets them; the new session's episodes have already started.
            out.CopyFrom(last)
            out.reset = bytes(n)
            del out.seeds[:]
            out.seeds.extend([0] * n)
            if self.autoreset_mode == AutoresetMode.NEXT_STEP:
                shard.pending = first
        else:
            # SAME_STEP: the new episodes start in this very step; the old ones are final_*.
            out.CopyFrom(first)
            out.final_observations = last.observations
            out.final_scores = last.scores
            out.final_lost = last.lost
            out.final_ticks = last.ticks
            out.final_action_masks = last.action_masks
            out.final_expert_actions = last.expert_actions
        out.rewards = bytes(4 * n)
        out.terminated = bytes(n)
        out.truncated = b"\x01" * n
        out.ClearField("stream_episodes")
        self._reconnected.append(shard)
        return out

    def _join(self, batches: list[pb.Batch], field: str) -> bytes:
        if len(batches) == 1:
            return getattr(batches[0], field)
        return b"".join([getattr(b, field) for b in batches])

    def _seeds(self, batches: list[pb.Batch]) -> np.ndarray:
        if len(batches) == 1:
            return np.array(batches[0].seeds, dtype=np.uint64)
        return np.array([s for b in batches for s in b.seeds], dtype=np.uint64)

    def _decode_common(
        self, batches: list[pb.Batch], prefix: str = "", present: np.ndarray | None = None
    ) -> tuple[np.ndarray, dict[str, Any]]:
        """Observations and infos of the state the batches return, or with ``prefix="final_"``
        of the episodes that ended (SAME_STEP); ``present`` is every info key's ``_key`` mask."""
        n = self.num_envs
        if present is None:
            present = np.ones(n, dtype=np.bool_)

        def field(name: str, dtype: str) -> np.ndarray:
            return np.frombuffer(self._join(batches, prefix + name), dtype=dtype)

        obs = field("observations", "i1").reshape(n, OBSERVATION_SIZE).astype(np.float32)
        info: dict[str, Any] = {
            "action_mask": field("action_masks", "?").reshape(n, NUM_ACTIONS).copy(),
            "score": field("scores", "<i4").astype(np.int64),
            "lost": field("lost", "<u4").astype(np.int64),
            "tick": field("ticks", "<u4").astype(np.int64),
        }
        if self.expert:
            info["expert_action"] = field("expert_actions", "u1").astype(np.int64)
        for key in list(info):
            info[f"_{key}"] = present.copy()
        return obs, info

    def _decode_step(self, batches: list[pb.Batch]):
        n = self.num_envs
        j = self._join
        obs, info = self._decode_common(batches)
        rewards = np.frombuffer(j(batches, "rewards"), dtype="<i4").astype(np.float64)
        terminated = np.frombuffer(j(batches, "terminated"), dtype=np.bool_).copy()
        truncated = np.frombuffer(j(batches, "truncated"), dtype=np.bool_).copy()
        reset = np.frombuffer(j(batches, "reset"), dtype=np.bool_)
        if reset.any():
            # The environments reset in this step carry their reset info: the seed.
            info["seed"] = self._seeds(batches)
            info["_seed"] = reset.copy()
            if self.autoreset_mode == AutoresetMode.SAME_STEP:
                final, final_info = self._decode_common(batches, "final_", reset)
                final_obs = np.full(n, None, dtype=object)
                for i in np.flatnonzero(reset):  # only the environments that just ended
                    final_obs[i] = final[i]
                info["final_obs"] = final_obs
                info["_final_obs"] = reset.copy()
                info["final_info"] = final_info
                info["_final_info"] = reset.copy()
        if self._reconnected:
            lost = np.zeros(n, dtype=np.bool_)
            for shard in self._reconnected:
                lost[shard.start : shard.stop] = True
            info["reconnected"] = lost
            info["_reconnected"] = lost.copy()
            self._reconnected = []
        return obs, rewards, terminated, truncated, info

    def render(self) -> tuple[Any, ...] | None:
        if self.render_mode is None:
            gym.logger.warn(
                "render() called without a render_mode; pass render_mode='ansi' or 'rgb_array'"
            )
            return None
        if self.render_mode == "ansi":
            return tuple(
                shard.conn.call(
                    "Render",
                    pb.RenderRequest(
                        session_id=shard.session_id, env_index=i, color=self.ansi_color
                    ),
                ).text
                for shard in self._shards
                for i in range(shard.size)
            )
        if any(s.last is None for s in self._shards):
            raise gym.error.ResetNeeded("call reset() before render()")
        batches = [s.last for s in self._shards]
        obs, info = self._decode_common(batches)
        lives = self.spec_proto.config.lives
        return tuple(
            _render.draw(
                obs[i], score=int(info["score"][i]), lost=int(info["lost"][i]), lives=lives
            )
            for i in range(self.num_envs)
        )

    def _close_sessions(self) -> None:
        for shard in self._shards:
            if shard.session_id is not None:
                close_session(shard.conn, shard.session_id)
                shard.session_id = None

    def close_extras(self, **kwargs: Any) -> None:
        self._close_sessions()
        self._endpoint.close()

"""The vector environment: N Diner Dash games in one batched session per server, the Gymnasium
adapter (arguments, autoreset modes, infos, the ``VectorEnv`` API) of a
:class:`~dinerdash._fleet.Fleet`, which holds the servers and sessions. Scale-out, failover and
moves: docs/client.md#failover-across-servers and docs/clusters.md#failover.
"""

from __future__ import annotations

import copy
import multiprocessing
import time
from collections.abc import Sequence
from typing import Any

import gymnasium as gym
import numpy as np
from gymnasium import spaces
from gymnasium.error import AlreadyPendingCallError, NoAsyncCallError
from gymnasium.vector import AutoresetMode, VectorEnv
from gymnasium.vector.utils import batch_space

from ._arguments import RENDER_MODES, Config, check_options, make_arrivals, make_config
from ._batch import Batch, decode, join
from ._endpoint import Endpoint
from ._fleet import Fleet
from ._proto import pb
from ._session import SessionCore, SessionOwner, check_actions
from .connection import ConnectOptions
from .errors import EnvClosed, InvalidArgument
from .game import observation_space

__all__ = ["DinerDashVectorEnv"]


class DinerDashVectorEnv(SessionOwner, VectorEnv):
    """``num_envs`` Diner Dash environments stepped together on one or more DinerDash servers.

    As :class:`dinerdash.env.DinerDashEnv`, every value with a leading axis of N: observations
    ``(N, 40) float32``, rewards ``(N,) float64``, each info key ``(N, ...)`` with its ``_key``
    mask (docs/client.md#the-infos). Each step is one ``Step`` call per server carrying the N
    actions as packed ``int32``; replies become numpy arrays with no loop over environments.

    Args:
        num_envs: number of environments N.
        address: a server, a list of servers, or a DNS name resolving to several: the
            environments are split into contiguous slices, one session per server (at most N).
            Default: ``DINERDASH_ADDRESS``, else a local server started and stopped on close.
        autoreset_mode: ``AutoresetMode.NEXT_STEP`` (default), ``SAME_STEP`` (``final_obs``,
            ``final_info``) or ``DISABLED`` (reset with ``options={"reset_mask": ...}``);
            ``metadata["autoreset_mode"]`` says which.
        failover_after, resolve_every: with ``reconnect=True`` and several servers, seconds a
            lost or silent server is borne with before its environments move to the others, and
            between resolutions of a DNS name (docs/client.md#failover-across-servers).
        max_episode_steps: shorthand for ``config["time_limit"]`` (the server truncates).
        expert, config, render_mode, ansi_color, connect and the connection keywords: as for the
            single env; ``render()`` returns one frame per environment.

    ``reset(seed=s)`` seeds environment ``i`` with ``s + i`` (or takes a list of N seeds);
    options: ``arrivals`` (one list or N), ``config`` (a full reset only), ``reset_mask``.
    :meth:`step_async` / :meth:`step_wait` pipeline a step (docs/client.md#pipelining-step_async-
    and-step_wait). An error about one environment carries its index here as ``env_index``.
    """

    #: Until ``__init__`` has opened the sessions: an env whose arguments were refused has nothing
    #: to close when it is collected (gymnasium's ``__del__`` closes every vector env).
    _closed = True
    _batched = True

    def __init__(
        self,
        num_envs: int = 1,
        address: str | Sequence[str] | None = None,
        *,
        expert: bool | str = False,
        autoreset_mode: AutoresetMode | str = AutoresetMode.NEXT_STEP,
        config: Config = None,
        max_episode_steps: int | None = None,
        render_mode: str | None = None,
        ansi_color: bool = False,
        connect: ConnectOptions | None = None,
        **connection: Any,
    ) -> None:
        mode = AutoresetMode(autoreset_mode)
        self.metadata = dict(render_modes=list(RENDER_MODES), render_fps=8, autoreset_mode=mode)
        self.autoreset_mode = mode
        self.num_envs = int(num_envs)
        self._settings = settings = self._take_arguments(
            self.num_envs, mode, address, expert, render_mode, ansi_color, connect, connection
        )
        config = make_config(config)
        if max_episode_steps is not None:
            config = pb.GameConfig() if config is None else copy.deepcopy(config)
            config.time_limit = int(max_episode_steps)
        settings.config = config
        self.failover_after = self._options.failover_after
        self._open()
        spec = self.spec_proto
        self.single_observation_space = observation_space(spec)
        self.single_action_space = spaces.Discrete(spec.num_actions)
        self.observation_space = batch_space(self.single_observation_space, self.num_envs)
        self.action_space = batch_space(self.single_action_space, self.num_envs)

    def _open(self) -> None:
        """Opens the fleet (at construction, and at a reset after close)."""
        #: The servers and sessions this env steps, for the bench and the tests that look inside a
        #: step; not a stable API.
        self.fleet = Fleet(self._options, self._settings)
        self.spec_proto: pb.Spec = self.fleet.spec
        #: A step_async() was sent and step_wait() has not collected it yet.
        self._pending = False
        self._seeds = np.zeros(self.num_envs, np.int64)  # each environment's episode seed
        self._everyone = np.ones(self.num_envs, np.bool_)  # copied for each step's `_key` masks
        self._closed = False
        self.closed = False  # Gymnasium's flag: close() calls close_extras only when False

    @property
    def _cores(self) -> list[SessionCore]:
        return self.fleet.cores

    @property
    def _endpoint(self) -> Endpoint:
        return self.fleet.endpoint

    @property
    def addresses(self) -> list[str]:
        """The servers serving now, in the order of the first environments they hold."""
        return list(dict.fromkeys(c.conn.address for c in self._cores))

    @property
    def lost_addresses(self) -> list[str]:
        """The servers given up (lost past ``failover_after``, or drained), in the order they
        were lost, until one is taken back."""
        return [self._endpoint.addresses[i] for i in self._endpoint.given_up]

    @property
    def failovers(self) -> int:
        """Servers given up for a failure since the env's sessions were opened."""
        return self._endpoint.failovers

    @property
    def rejoins(self) -> int:
        """Servers taken back or in (a DNS name's new replicas) since the sessions opened."""
        return self._endpoint.rejoins

    @property
    def moves(self) -> int:
        """Environments moved exactly, by Snapshot and Restore, to another server; not a
        failover's nor a refused Restore's, whose episodes restart (docs/client.md)."""
        return self.fleet.moves

    @property
    def env_slices(self) -> list[tuple[str, slice]]:
        """Which server holds which environments: one entry per session, in environment order."""
        return [(c.conn.address, slice(c.start, c.stop)) for c in self._cores]

    @property
    def session_ids(self) -> list[str | None]:
        return [c.session_id for c in self._cores]

    def reset(
        self, *, seed: int | Sequence[int] | None = None, options: dict[str, Any] | None = None
    ) -> tuple[np.ndarray, dict[str, Any]]:
        seeds = None
        if seed is None or isinstance(seed, (int, np.integer)):
            super().reset(seed=None if seed is None else int(seed))
        else:
            seeds, seed = [int(s) for s in seed], None
            if len(seeds) != self.num_envs:
                raise ValueError(
                    f"seed: expected an int or {self.num_envs} seeds, got {len(seeds)}"
                )
        options = check_options(options, ("arrivals", "config", "reset_mask"))
        self._check_idle("reset()")
        if self._closed:
            if options.get("reset_mask") is not None:
                raise EnvClosed("a reset_mask after close(): the new sessions need a full reset")
            self._open()  # reuse after close: new sessions (and a new local server if needed)
        mask = self._reset_mask(options.get("reset_mask"), options.get("config"))
        arrivals = make_arrivals(options.get("arrivals"), self.num_envs)
        if len(self._cores) > 1 and len(arrivals) not in (0, 1, self.num_envs):
            raise InvalidArgument(
                f"arrivals: expected one list or {self.num_envs} lists (one per environment), "
                f"got {len(arrivals)}"
            )
        config = make_config(options.get("config"))
        if config is not None:
            self._settings.config = config

        given = {"seed": seed, "seeds": seeds, "arrivals": arrivals, "config": config}
        called = self.fleet.reset(given, mask)
        batch = join(self.fleet.batches())
        obs, info = decode(batch, self.expert)
        info["seed"] = batch["seeds"].astype(np.int64)  # as SyncVectorEnv; torch has no uint64
        info["_seed"] = batch["reset"] & called
        self._seeds = np.where(info["_seed"], info["seed"], self._seeds)
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
        for core in self._cores:
            if core.last is None and not reset_mask[core.start : core.stop].all():
                kept = core.start + int(np.flatnonzero(~reset_mask[core.start : core.stop])[0])
                raise ValueError(
                    f"environment {kept} has never been reset: include it in reset_mask"
                )
        return reset_mask

    def step(
        self, actions: Any
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, dict[str, Any]]:
        """One step of every environment: :meth:`step_async` and :meth:`step_wait` in a row."""
        wire = check_actions(actions, self.num_envs)
        self._check_idle("step()")
        self._check_open("step()")
        if self.fleet.blocking():
            return self.decode_step(self.fleet.step(wire))
        self.fleet.start(wire)
        self._pending = True
        return self.step_wait()

    def step_async(self, actions: Any) -> None:
        """Checks and sends this step's ``actions`` and returns at once; :meth:`step_wait`
        returns its results. Any other call but ``close()`` before that raises
        ``AlreadyPendingCallError`` (docs/client.md#pipelining-step_async-and-step_wait)."""
        wire = check_actions(actions, self.num_envs)
        self._check_idle("step_async()")
        self._check_open("step_async()")
        self.fleet.start(wire)
        self._pending = True

    def step_wait(
        self, timeout: float | None = None
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, dict[str, Any]]:
        """The results of the step :meth:`step_async` sent, as :meth:`step` returns them. No
        reply within ``timeout`` seconds: ``multiprocessing.TimeoutError``, the step still
        pending (call ``step_wait`` again); none sent: ``NoAsyncCallError``."""
        if not self._pending:
            raise NoAsyncCallError("step_wait() without a step_async() before it", "step")
        if timeout is not None:
            deadline = time.monotonic() + timeout
            if not all(core.step_ready(deadline) for core in self._cores):
                raise multiprocessing.TimeoutError(
                    f"step_wait(): no reply within {timeout:g} s; the step is still "
                    "pending, call step_wait() again"
                )
        self.fleet.wait()  # an interrupted wait (Ctrl-C) leaves the step pending
        self._pending = False
        return self.decode_step(self.fleet.finish())

    def _check_idle(self, what: str) -> None:
        if self._pending:
            raise AlreadyPendingCallError(
                f"{what} while a step_async() awaits its step_wait(); call step_wait() first",
                "step",
            )

    def action_masks(self) -> np.ndarray:
        """``(N, 57) bool``: the actions that have an effect in each environment's current state
        (what sb3-contrib's MaskablePPO asks for; ``info["action_mask"]`` holds the same)."""
        self._check_idle("action_masks()")
        self._check_open("action_masks()")
        if any(c.last is None for c in self._cores):
            raise gym.error.ResetNeeded("call reset() before action_masks()")
        return join(self.fleet.batches())["action_masks"].copy()

    def decode_step(self, batches: list[Batch]):
        """The step's ``(obs, rewards, terminated, truncated, info)`` from the sessions' replies
        (``batches``, in environment order). It advances the episode seeds: only the bench calls
        it besides :meth:`step` and :meth:`step_wait`, to time it."""
        n = self.num_envs
        batch = join(batches)
        everyone = self._everyone
        obs, info = decode(batch, self.expert, present=everyone)
        rewards = batch["rewards"].astype(np.float64)
        terminated = batch["terminated"].copy()
        truncated = batch["truncated"].copy()
        reset = batch.get("reset")
        resets = reset is not None and np.count_nonzero(reset) > 0
        # Every step's info has reset's keys (TorchRL reads them once): each environment's
        # episode seed, as a SyncVectorEnv of DinerDashEnv reports it.
        ended_seeds = self._seeds
        if resets:
            self._seeds = np.where(reset, batch["seeds"].astype(np.int64), self._seeds)
        info["seed"], info["_seed"] = self._seeds.copy(), everyone.copy()
        if resets and self.autoreset_mode == AutoresetMode.SAME_STEP:
            final, final_info = decode(batch, self.expert, "final_", reset)
            final_info["seed"] = np.where(reset, ended_seeds, 0)
            final_info["_seed"] = reset.copy()
            final_obs = np.full(n, None, dtype=object)
            for i in np.flatnonzero(reset):  # only the environments that just ended
                final_obs[i] = final[i]
            info["final_obs"], info["_final_obs"] = final_obs, reset.copy()
            info["final_info"], info["_final_info"] = final_info, reset.copy()
        cut = [c for c in self._cores if c.reconnected]
        if cut:
            lost = np.zeros(n, dtype=np.bool_)
            for core in cut:
                core.take_reconnected()
                lost[core.start : core.stop] = True
            info["reconnected"] = lost
            info["_reconnected"] = lost.copy()
        return obs, rewards, terminated, truncated, info

    def _shown(self) -> tuple[Any, Any, Any]:
        if any(c.last is None for c in self._cores):
            raise gym.error.ResetNeeded("call reset() before render()")
        obs, info = decode(join(self.fleet.batches()), self.expert)
        return obs, info["score"], info["lost"]

    def close_extras(self, **kwargs: Any) -> None:
        """Closes the sessions (and a local server this env started); a later full ``reset()``
        opens new ones."""
        if not self._closed:
            self._pending = False  # the cores' threads end as the sessions close
            self.fleet.close()
            self._closed = True

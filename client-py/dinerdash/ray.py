"""Ray and RLlib: servers placed by Ray, one batched session per EnvRunner, masked PPO (needs the
``dinerdash[ray]`` extra).

::

    import ray
    from dinerdash.ray import masked_ppo, start_servers

    ray.init()                                   # or ray.init(address="auto") on a cluster
    with start_servers() as pool:                # one dinerdash-server per Ray node
        algo = masked_ppo(pool.addresses).build()
        for _ in range(100):
            algo.train()

- :func:`start_servers` runs each ``dinerdash-server`` under a Ray actor pinned to its node; the
  server listens on the node's IP on a free port, and if it dies (its process or its actor) Ray
  restarts the actor, which starts the server again *on the same port*, so clients built with
  ``reconnect=True`` find it again at the address they know. :class:`ServerPool` holds the
  actors: ``pool.addresses``, ``pool.close()``, a context manager.
- :func:`register` registers the RLlib environment ``"DinerDash-v0"``: with
  ``gym_env_vectorize_mode=gym.VectorizeMode.VECTOR_ENTRY_POINT`` each EnvRunner gets one
  :class:`~dinerdash.DinerDashVectorEnv` of ``num_envs_per_env_runner`` environments (one
  session, one round trip per step), instead of RLlib's default of one ``gymnasium.make`` env,
  and one round trip, per environment.
- :func:`masked_ppo` is an RLlib (new API stack) ``PPOConfig`` on that environment with
  :class:`MaskedPPOTorchRLModule`, which never samples an illegal action.

The binary: each actor looks for ``dinerdash-server`` on its own node as the embedded default
does (:func:`dinerdash.server.find_server_binary`: ``DINERDASH_SERVER``, the ``dinerdash-server``
wheel, ``PATH``). On a real cluster either install ``dinerdash[ray,server]`` on every node, or
point every node at a binary: ``ray.init(runtime_env={"env_vars": {"DINERDASH_SERVER": path}})``
with ``path`` valid on every node.
"""

from __future__ import annotations

import os
import sys
import tempfile
import threading
import time
import uuid
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import gymnasium as gym
import numpy as np
from gymnasium import spaces
from gymnasium.vector import AutoresetMode, VectorWrapper

from .env import DinerDashEnv
from .errors import LocalServerError
from .vector import DinerDashVectorEnv

try:
    import ray
    import torch
    from ray.rllib.algorithms.ppo import PPOConfig
    from ray.rllib.algorithms.ppo.torch.default_ppo_torch_rl_module import (
        DefaultPPOTorchRLModule,
    )
    from ray.rllib.core.columns import Columns
    from ray.rllib.core.rl_module.rl_module import RLModuleSpec
    from ray.rllib.env.env_context import EnvContext
    from ray.tune.registry import register_env
    from ray.util.scheduling_strategies import NodeAffinitySchedulingStrategy
except ImportError as e:  # pragma: no cover - depends on the installed extras
    raise ImportError(
        f"dinerdash.ray needs Ray with RLlib and torch ({e}): pip install 'dinerdash[ray]'"
    ) from e

__all__ = [
    "ENV_NAME",
    "SERVER_RESOURCE",
    "MaskedObservation",
    "MaskedPPOTorchRLModule",
    "ServerPool",
    "ServerPoolError",
    "VectorMaskedObservation",
    "make_env",
    "masked_ppo",
    "register",
    "start_servers",
]

#: The RLlib environment :func:`register` registers.
ENV_NAME = "DinerDash-v0"
#: A node started with this custom resource (``ray start --resources='{"dinerdash_server": 1}'``)
#: is a server node: when any node has it, :func:`start_servers` uses only those.
SERVER_RESOURCE = "dinerdash_server"
#: How often Ray restarts a server that died (its actor is restarted, the server with it).
MAX_RESTARTS = 20
#: The ``env_config`` keys :func:`make_env` knows (RLlib adds ``num_envs`` itself).
ENV_CONFIG_KEYS = ("address", "token", "timeout", "reconnect", "expert", "mask_observation")
#: Seconds a restarted server retries its old port while the killed one lets go of it.
_PORT_RETRY_SECONDS = 15.0


class ServerPoolError(LocalServerError):
    """The servers of a :class:`ServerPool` could not be placed or started."""


# -- servers ------------------------------------------------------------------------------------


class _ServerActor:
    """One ``dinerdash-server`` on this actor's node. Its port is kept in a file named by the
    server's key, so that the actor Ray restarts after a crash starts the server on the same
    port. When the server process exits without :meth:`stop`, the actor exits too, so that Ray
    restarts both."""

    def __init__(self, key: str, token: str | None, args: list[str]) -> None:
        from .server import LocalServer

        self._stopping = False
        self._port_file = Path(tempfile.gettempdir()) / "dinerdash-ray" / f"{key}.port"
        port = int(self._port_file.read_text()) if self._port_file.is_file() else 0
        if token is not None:
            # Through the environment, not the command line: ps shows no token.
            os.environ["DINERDASH_AUTH_TOKEN"] = token
        host = ray.util.get_node_ip_address()
        deadline = time.monotonic() + _PORT_RETRY_SECONDS
        while True:
            try:
                self._server = LocalServer(host=host, port=port, args=args)
                break
            except LocalServerError:
                # A restart: the killed server's port may not be free yet.
                if port == 0 or time.monotonic() > deadline:
                    raise
                time.sleep(0.2)
        self._port_file.parent.mkdir(parents=True, exist_ok=True)
        self._port_file.write_text(self._server.address.rsplit(":", 1)[1])
        threading.Thread(target=self._watch, name="dinerdash-server-watch", daemon=True).start()

    def _watch(self) -> None:
        process = self._server.process
        process.wait()
        if not self._stopping:
            print(
                f"dinerdash-server at {self._server.address} exited with status "
                f"{process.returncode}; its actor exits so that Ray restarts both",
                file=sys.stderr,
                flush=True,
            )
            os._exit(1)

    def address(self) -> str:
        return self._server.address

    def pid(self) -> int:
        return self._server.pid

    def node_id(self) -> str:
        return ray.get_runtime_context().get_node_id()

    def stop(self) -> None:
        self._stopping = True
        self._server.stop()
        self._port_file.unlink(missing_ok=True)


def _server_flags(flags: Mapping[str, Any]) -> list[str]:
    """``max_sessions=8`` -> ``--max-sessions 8``; ``True`` a bare flag, ``False``/``None``
    nothing."""
    args: list[str] = []
    for name, value in flags.items():
        flag = "--" + name.replace("_", "-")
        if flag in ("--host", "--port", "--auth-token"):
            raise TypeError(
                f"start_servers(): {name}= is chosen by the pool (the node's address, a free "
                "port, token=)"
            )
        if value is None or value is False:
            continue
        args.append(flag)
        if value is not True:
            args.append(str(value))
    return args


def _server_nodes() -> list[dict[str, Any]]:
    """The alive nodes that run servers: those with :data:`SERVER_RESOURCE` if any has it,
    else all of them; in a fixed order (address, then node id)."""
    nodes = [n for n in ray.nodes() if n.get("Alive")]
    marked = [n for n in nodes if n.get("Resources", {}).get(SERVER_RESOURCE, 0) > 0]
    chosen = marked or nodes
    return sorted(chosen, key=lambda n: (n["NodeManagerAddress"], n["NodeID"]))


class ServerPool:
    """``dinerdash-server`` processes run by Ray actors, one or more per node.

    Attributes:
        addresses: ``host:port`` of each server (the node's IP, the port the server picked).
        node_ids: the Ray node of each server.
        actors: the actor handles (methods ``address``, ``pid``, ``node_id``, ``stop``).
    """

    def __init__(self, actors: list[Any], addresses: list[str], node_ids: list[str]) -> None:
        self.actors = actors
        self.addresses = addresses
        self.node_ids = node_ids
        self._closed = False

    def pids(self) -> list[int]:
        """The servers' process ids (each on its own node)."""
        return ray.get([a.pid.remote() for a in self.actors])

    def close(self, timeout: float = 30.0) -> None:
        """Stops every server and its actor (no restart); safe to call twice."""
        if self._closed:
            return
        self._closed = True
        pending = [a.stop.remote() for a in self.actors]
        try:
            ray.wait(pending, num_returns=len(pending), timeout=timeout)
        finally:
            for actor in self.actors:
                ray.kill(actor, no_restart=True)

    def __enter__(self) -> ServerPool:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def __len__(self) -> int:
        return len(self.addresses)

    def __repr__(self) -> str:
        state = "closed" if self._closed else "running"
        return f"ServerPool({self.addresses!r}, {state})"


def start_servers(
    per_node: int = 1,
    num_servers: int | None = None,
    token: str | None = None,
    **server_flags: Any,
) -> ServerPool:
    """Starts ``dinerdash-server`` processes on the Ray cluster and returns their
    :class:`ServerPool` once every one listens.

    Each server runs under its own actor, pinned to its node (a hard node affinity, so that a
    restart lands on the same node and the same port). The servers' CPUs are not reserved from
    Ray (the actors ask for 0 CPUs): Ray's CPUs stay for EnvRunners and learners.

    Args:
        per_node: servers on each node. The nodes are those with the custom resource
            :data:`SERVER_RESOURCE`, or, when none has it, every alive node.
        num_servers: the number of servers in all, dealt over the nodes in turn (overrides
            ``per_node``).
        token: the servers require ``authorization: Bearer <token>`` (``--auth-token``); give
            the clients the same ``token``.
        server_flags: more server flags, ``max_sessions=20000`` for ``--max-sessions 20000``
            (``True`` for a bare flag).

    Raises:
        ServerPoolError: no node, or a server that did not start (the message says why: no
            binary on that node, a bad flag ...).
    """
    if not ray.is_initialized():
        ray.init()
    if per_node < 1:
        raise ValueError(f"per_node must be at least 1, got {per_node}")
    args = _server_flags(server_flags)
    nodes = _server_nodes()
    if not nodes:
        raise ServerPoolError("start_servers(): the Ray cluster has no alive node")
    count = len(nodes) * per_node if num_servers is None else int(num_servers)
    if count < 1:
        raise ValueError(f"num_servers must be at least 1, got {num_servers}")
    remote = ray.remote(_ServerActor).options  # options per actor: its node
    actors = []
    placed = []
    for i in range(count):
        node = nodes[i % len(nodes)]
        actor = remote(
            num_cpus=0,
            max_restarts=MAX_RESTARTS,
            scheduling_strategy=NodeAffinitySchedulingStrategy(node["NodeID"], soft=False),
        ).remote(uuid.uuid4().hex, token, args)
        actors.append(actor)
        placed.append(node["NodeID"])
    try:
        addresses = ray.get([a.address.remote() for a in actors])
    except ray.exceptions.RayActorError as e:
        for actor in actors:
            ray.kill(actor, no_restart=True)
        raise ServerPoolError(f"start_servers(): a server did not start: {e}") from None
    return ServerPool(actors, addresses, placed)


# -- the RLlib environment ----------------------------------------------------------------------


def _dict_space(observations: spaces.Box, num_actions: int) -> spaces.Dict:
    return spaces.Dict(
        {
            "observations": observations,
            "action_mask": spaces.Box(0.0, 1.0, (num_actions,), np.float32),
        }
    )


class MaskedObservation(gym.Wrapper):
    """A :class:`~dinerdash.DinerDashEnv` whose observation is RLlib's masking ``Dict``:
    ``{"observations": (40,) float32, "action_mask": (57,) float32 of 0/1}`` (the mask of the
    same state, ``info["action_mask"]``, which the info then no longer carries)."""

    def __init__(self, env: gym.Env) -> None:
        super().__init__(env)
        self.observation_space = _dict_space(env.observation_space, int(env.action_space.n))

    @staticmethod
    def _masked(obs: np.ndarray, info: dict[str, Any]) -> dict[str, np.ndarray]:
        mask = info.pop("action_mask")
        return {"observations": obs, "action_mask": mask.astype(np.float32)}

    def reset(self, **kwargs: Any):
        obs, info = self.env.reset(**kwargs)
        return self._masked(obs, info), info

    def step(self, action: Any):
        obs, reward, terminated, truncated, info = self.env.step(action)
        return self._masked(obs, info), reward, terminated, truncated, info


class VectorMaskedObservation(VectorWrapper):
    """The same ``Dict`` observation for a :class:`~dinerdash.DinerDashVectorEnv`: every value
    with a leading axis of ``num_envs``."""

    def __init__(self, env: DinerDashVectorEnv) -> None:
        super().__init__(env)
        n = int(env.single_action_space.n)
        self.single_observation_space = _dict_space(env.single_observation_space, n)
        self.observation_space = gym.vector.utils.batch_space(
            self.single_observation_space, env.num_envs
        )

    @staticmethod
    def _masked(obs: np.ndarray, info: dict[str, Any]) -> dict[str, np.ndarray]:
        mask = info.pop("action_mask")
        info.pop("_action_mask", None)
        return {"observations": obs, "action_mask": mask.astype(np.float32)}

    def reset(self, **kwargs: Any):
        obs, info = self.env.reset(**kwargs)
        return self._masked(obs, info), info

    def step(self, actions: Any):
        obs, rewards, terminated, truncated, info = self.env.step(actions)
        return self._masked(obs, info), rewards, terminated, truncated, info


def _runner_index(config: Mapping[str, Any]) -> tuple[int, int]:
    """``(worker_index, num_workers)`` of the EnvRunner building this env.

    RLlib 2.60 calls the vector entry point with ``env_ctx | {"num_envs": n}``, a plain dict
    that has lost the ``EnvContext``'s ``worker_index``; the ``EnvContext`` itself is a local
    of RLlib's callers (``SingleAgentEnvRunner.make_env`` and its entry-point lambda), read
    from there. Outside RLlib: ``(0, 0)``."""
    if isinstance(config, EnvContext):
        return config.worker_index, config.num_workers or 0
    frame = sys._getframe(1)
    for _ in range(12):
        if frame is None:
            break
        ctx = frame.f_locals.get("env_ctx")
        if isinstance(ctx, EnvContext):
            return ctx.worker_index, ctx.num_workers or 0
        frame = frame.f_back
    return 0, 0


def _runner_addresses(
    address: str | Sequence[str] | None, worker_index: int, num_workers: int
) -> str | list[str] | None:
    """The servers of EnvRunner ``worker_index`` (1..num_workers; 0 the local one): with more
    servers than EnvRunners, its share of them (every ``num_workers``-th); else one, in turn."""
    if address is None or isinstance(address, str):
        return address
    servers = list(address)
    if not servers:
        raise ValueError("env_config['address']: an empty list")
    runners = max(1, num_workers)
    k = max(0, worker_index - 1) % runners
    if len(servers) >= runners:
        return servers[k::runners]
    return servers[k % len(servers)]


def make_env(config: Mapping[str, Any]) -> gym.Env | gym.vector.VectorEnv:
    """The entry point of the RLlib environment ``"DinerDash-v0"`` (see :func:`register`).

    With ``num_envs`` in ``config`` (RLlib's ``VECTOR_ENTRY_POINT`` mode) one
    :class:`~dinerdash.DinerDashVectorEnv` of that many environments; else one
    :class:`~dinerdash.DinerDashEnv` (RLlib's default mode makes one per sub-environment).
    Autoreset is ``NEXT_STEP``, RLlib's convention.

    ``config`` keys (RLlib's ``env_config``): ``address`` (a server, or a list spread over the
    EnvRunners by ``worker_index``: each gets its share), ``token``, ``timeout``, ``reconnect``
    (default ``False``), ``expert`` (``True``/``"planner"``: ``info["expert_action"]``),
    ``mask_observation`` (default ``True``: the ``Dict`` observation of
    :class:`MaskedObservation`).
    """
    unknown = sorted(set(config) - {*ENV_CONFIG_KEYS, "num_envs"})
    if unknown:
        raise ValueError(
            f"env_config: unknown key(s) {unknown}; DinerDash-v0 knows {list(ENV_CONFIG_KEYS)}"
        )
    worker_index, num_workers = _runner_index(config)
    address = _runner_addresses(config.get("address"), worker_index, num_workers)
    kwargs: dict[str, Any] = {
        "address": address,
        "token": config.get("token"),
        "timeout": config.get("timeout"),
        "reconnect": bool(config.get("reconnect", False)),
        "expert": config.get("expert", False),
    }
    mask = bool(config.get("mask_observation", True))
    if "num_envs" in config:
        venv = DinerDashVectorEnv(
            int(config["num_envs"]), autoreset_mode=AutoresetMode.NEXT_STEP, **kwargs
        )
        return VectorMaskedObservation(venv) if mask else venv
    if not isinstance(address, (str, type(None))):
        address = address[0]  # one environment, one server: the first of this runner's share
    env = DinerDashEnv(**{**kwargs, "address": address})
    return MaskedObservation(env) if mask else env


def register() -> None:
    """Registers the RLlib environment ``"DinerDash-v0"`` (:func:`make_env`) with Ray Tune's
    registry, which every process of the cluster reads. Use it with
    ``config.env_runners(gym_env_vectorize_mode=gym.VectorizeMode.VECTOR_ENTRY_POINT)`` for one
    batched session per EnvRunner (:func:`masked_ppo` does)."""
    register_env(ENV_NAME, make_env)


# -- masked PPO ---------------------------------------------------------------------------------

#: The logit of an illegal action (as the agents' masked losses use).
ILLEGAL_LOGIT = -1e9
#: The value head predicts returns in units of this many points (rewards are multiples of 10, a
#: group that runs away costs 500): PPO's value loss sees returns of about 1.
VALUE_SCALE = 100.0


class MaskedPPOTorchRLModule(DefaultPPOTorchRLModule):
    """RLlib's default PPO module on the ``Dict`` observation of :class:`MaskedObservation`:
    the networks see ``observations`` divided by the observation space's upper bounds, and
    the logits of the actions ``action_mask`` forbids are :data:`ILLEGAL_LOGIT`, so that
    exploration, inference and the PPO loss only ever weigh legal actions.

    The value head's output is multiplied by ``model_config["value_scale"]`` (default
    :data:`VALUE_SCALE`); :func:`masked_ppo` divides the value loss's coefficient and clip by
    its square, which is PPO on rewards divided by the scale.
    """

    def __init__(self, *, observation_space: gym.Space | None = None, **kwargs: Any) -> None:
        if not isinstance(observation_space, spaces.Dict) or set(observation_space.spaces) != {
            "observations",
            "action_mask",
        }:
            raise ValueError(
                "MaskedPPOTorchRLModule needs the Dict observation with keys 'observations' and "
                f"'action_mask' (env_config mask_observation=True), got {observation_space}"
            )
        self._dict_space = observation_space
        inner = observation_space["observations"]
        high = np.where(np.isfinite(inner.high) & (inner.high > 0), inner.high, 1.0)
        self._scale = torch.as_tensor(high, dtype=torch.float32)
        super().__init__(observation_space=inner, **kwargs)

    def setup(self) -> None:
        super().setup()
        # The networks are built for the inner Box; the module takes the Dict.
        self.observation_space = self._dict_space

    def _split(self, batch: dict[str, Any]) -> tuple[Any, dict[str, Any]]:
        obs = batch[Columns.OBS]
        if not isinstance(obs, Mapping):
            raise ValueError("MaskedPPOTorchRLModule: the batch's observations are not the Dict")
        inner = dict(batch)
        inner[Columns.OBS] = obs["observations"] / self._scale.to(obs["observations"].device)
        return obs["action_mask"], inner

    @staticmethod
    def _mask(out: dict[str, Any], mask: Any) -> dict[str, Any]:
        logits = out[Columns.ACTION_DIST_INPUTS]
        out[Columns.ACTION_DIST_INPUTS] = torch.where(
            mask > 0.5, logits, torch.full_like(logits, ILLEGAL_LOGIT)
        )
        return out

    def _forward(self, batch: dict[str, Any], **kwargs: Any) -> dict[str, Any]:
        mask, inner = self._split(batch)
        return self._mask(super()._forward(inner, **kwargs), mask)

    def _forward_train(self, batch: dict[str, Any], **kwargs: Any) -> dict[str, Any]:
        mask, inner = self._split(batch)
        return self._mask(super()._forward_train(inner, **kwargs), mask)

    def compute_values(self, batch: dict[str, Any], embeddings: Any = None) -> Any:
        inner = batch if embeddings is not None else self._split(batch)[1]
        scale = float(self.model_config.get("value_scale", VALUE_SCALE))
        return super().compute_values(inner, embeddings) * scale


def masked_ppo(
    addresses: str | Sequence[str],
    num_env_runners: int = 2,
    num_envs_per_env_runner: int = 64,
    **ppo_overrides: Any,
) -> PPOConfig:
    """An RLlib PPO config (new API stack) that trains :class:`MaskedPPOTorchRLModule` on the
    servers at ``addresses``: ``masked_ppo(pool.addresses).build().train()``.

    ``num_env_runners`` EnvRunners, each with one batched session of
    ``num_envs_per_env_runner`` environments (the servers spread over the EnvRunners, see
    :func:`make_env`); a local learner (add ``.learners(num_learners=..,
    num_gpus_per_learner=..)`` for remote ones). The hyper-parameters are those of the
    agents' JAX PPO (``dinerdash_agents.ppo.PPOConfig``: a 128x128 tanh network, lr 3e-4,
    gamma 0.995, lambda 0.95, clip 0.2, entropy 0.01, 2 epochs of 4 minibatches, 32 steps per
    environment per batch).

    The environments reconnect (``env_config`` ``reconnect=True``): a server that
    :func:`start_servers` restarts is found again on its port, its episodes end truncated.

    ``ppo_overrides``: any ``AlgorithmConfig`` setting, applied last (``lr=1e-4``,
    ``train_batch_size_per_learner=...``); an ``env_config`` is merged into this one
    (``env_config={"token": "...", "timeout": 30}``).
    """
    register()
    env_config: dict[str, Any] = {
        "address": addresses if isinstance(addresses, str) else list(addresses),
        # A server that dies is restarted by Ray on its port (start_servers): wait for it.
        "reconnect": True,
    }
    overrides = dict(ppo_overrides)
    env_config.update(overrides.pop("env_config", None) or {})
    scale = VALUE_SCALE
    batch = max(1, num_env_runners) * num_envs_per_env_runner * 32
    config = (
        PPOConfig()
        .environment(ENV_NAME, env_config=env_config)
        .env_runners(
            num_env_runners=num_env_runners,
            num_envs_per_env_runner=num_envs_per_env_runner,
            gym_env_vectorize_mode=gym.VectorizeMode.VECTOR_ENTRY_POINT,
            rollout_fragment_length="auto",
        )
        .rl_module(
            rl_module_spec=RLModuleSpec(
                module_class=MaskedPPOTorchRLModule,
                model_config={
                    "fcnet_hiddens": [128, 128],
                    "fcnet_activation": "tanh",
                    "vf_share_layers": False,
                    "value_scale": scale,
                },
            )
        )
        .training(
            lr=3e-4,
            gamma=0.995,
            lambda_=0.95,
            clip_param=0.2,
            entropy_coeff=0.01,
            vf_loss_coeff=0.5 / scale**2,
            vf_clip_param=10.0 * scale**2,
            use_kl_loss=False,
            grad_clip=0.5,
            num_epochs=2,
            train_batch_size_per_learner=batch,
            minibatch_size=max(1, batch // 4),
        )
    )
    if overrides:
        config.update_from_dict(overrides)
    return config

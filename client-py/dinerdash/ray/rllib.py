"""RLlib on DinerDash: the environment ``"DinerDash-v0"`` (one batched session per EnvRunner, the
action mask in a ``Dict`` observation), :class:`MaskedPPOTorchRLModule` and :func:`masked_ppo`
(docs/clusters.md#the-environment-register).
"""

from __future__ import annotations

import sys
from collections.abc import Mapping, Sequence
from typing import Any

import gymnasium as gym
import numpy as np
from gymnasium import spaces
from gymnasium.vector import AutoresetMode, VectorWrapper

from ..env import DinerDashEnv
from ..vector import DinerDashVectorEnv

try:
    import torch
    from ray.rllib.algorithms.ppo import PPOConfig
    from ray.rllib.algorithms.ppo.torch.default_ppo_torch_rl_module import (
        DefaultPPOTorchRLModule,
    )
    from ray.rllib.core.columns import Columns
    from ray.rllib.core.rl_module.rl_module import RLModuleSpec
    from ray.rllib.env.env_context import EnvContext
    from ray.tune.registry import register_env
except ImportError as e:  # pragma: no cover - depends on the installed extras
    raise ImportError(
        f"dinerdash.ray needs Ray with RLlib and torch ({e}): pip install 'dinerdash[ray]'"
    ) from e

__all__ = [
    "ENV_CONFIG_KEYS",
    "ENV_NAME",
    "ILLEGAL_LOGIT",
    "VALUE_SCALE",
    "MaskedObservation",
    "MaskedPPOTorchRLModule",
    "VectorMaskedObservation",
    "make_env",
    "masked_ppo",
    "register",
]

#: The RLlib environment :func:`register` registers.
ENV_NAME = "DinerDash-v0"
#: The ``env_config`` keys :func:`make_env` knows (RLlib adds ``num_envs`` itself).
ENV_CONFIG_KEYS = (
    "address",
    "token",
    "timeout",
    "reconnect",
    "expert",
    "mask_observation",
    "failover_after",
    "reconnect_timeout",
)


def _dict_space(observations: spaces.Box, num_actions: int) -> spaces.Dict:
    return spaces.Dict(
        {
            "observations": observations,
            "action_mask": spaces.Box(0.0, 1.0, (num_actions,), np.float32),
        }
    )


class _Masking:
    """``reset()`` and ``step()`` of both wrappers: the observation becomes RLlib's masking
    ``Dict`` and the info gives up its ``action_mask`` (and ``_action_mask``)."""

    env: Any

    @staticmethod
    def _masked(obs: np.ndarray, info: dict[str, Any]) -> dict[str, np.ndarray]:
        mask = info.pop("action_mask")
        info.pop("_action_mask", None)
        return {"observations": obs, "action_mask": mask.astype(np.float32)}

    def reset(self, **kwargs: Any):
        obs, info = self.env.reset(**kwargs)
        return self._masked(obs, info), info

    def step(self, action: Any):
        obs, reward, terminated, truncated, info = self.env.step(action)
        return self._masked(obs, info), reward, terminated, truncated, info


class MaskedObservation(_Masking, gym.Wrapper):
    """A :class:`~dinerdash.DinerDashEnv` whose observation is RLlib's masking ``Dict``:
    ``{"observations": (40,) float32, "action_mask": (57,) float32 of 0/1}`` (the mask of the
    same state, ``info["action_mask"]``, which the info then no longer carries)."""

    def __init__(self, env: gym.Env) -> None:
        super().__init__(env)
        self.observation_space = _dict_space(env.observation_space, int(env.action_space.n))


class VectorMaskedObservation(_Masking, VectorWrapper):
    """The same ``Dict`` observation for a :class:`~dinerdash.DinerDashVectorEnv`: every value
    with a leading axis of ``num_envs``."""

    def __init__(self, env: DinerDashVectorEnv) -> None:
        super().__init__(env)
        n = int(env.single_action_space.n)
        self.single_observation_space = _dict_space(env.single_observation_space, n)
        self.observation_space = gym.vector.utils.batch_space(
            self.single_observation_space, env.num_envs
        )


def _runner_index(config: Mapping[str, Any]) -> tuple[int, int]:
    """``(worker_index, num_workers)`` of the EnvRunner building this env, read from the
    ``EnvContext`` a local of RLlib's callers holds when ``config`` has lost it (RLlib 2.60's
    vector entry point); outside RLlib ``(0, 0)``."""
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
    """The entry point of the RLlib environment ``"DinerDash-v0"``: with ``num_envs`` in
    ``config`` (``VECTOR_ENTRY_POINT`` mode) one :class:`~dinerdash.DinerDashVectorEnv` of that
    many environments, else one :class:`~dinerdash.DinerDashEnv`; autoreset ``NEXT_STEP``.
    ``config``: the keys of :data:`ENV_CONFIG_KEYS` (docs/clusters.md#the-environment-register).
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
    for key in ("failover_after", "reconnect_timeout"):
        if key in config:
            kwargs[key] = config[key]
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
    registry, which every process of the cluster reads."""
    register_env(ENV_NAME, make_env)


# -- masked PPO ---------------------------------------------------------------------------------

#: The logit of an illegal action (as the agents' masked losses use).
ILLEGAL_LOGIT = -1e9
#: The value head predicts returns in units of this many points (rewards are multiples of 10, a
#: group that runs away costs 500): PPO's value loss sees returns of about 1.
VALUE_SCALE = 100.0


class MaskedPPOTorchRLModule(DefaultPPOTorchRLModule):
    """RLlib's default PPO module on the ``Dict`` observation of :class:`MaskedObservation`: the
    networks see ``observations`` divided by their upper bounds, illegal actions' logits are
    :data:`ILLEGAL_LOGIT`, and the value head's output is multiplied by
    ``model_config["value_scale"]`` (default :data:`VALUE_SCALE`)."""

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
    servers at ``addresses`` with the agents' JAX PPO's hyper-parameters:
    ``masked_ppo(pool.addresses).build_algo().train()`` (docs/clusters.md#masked-ppo-masked_ppo).
    ``num_env_runners`` EnvRunners, each with one batched session of ``num_envs_per_env_runner``
    environments that reconnect; ``ppo_overrides``: any ``AlgorithmConfig`` setting, applied
    last (an ``env_config`` is merged into this one).
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

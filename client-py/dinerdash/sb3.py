"""stable-baselines3 on one batched session: :func:`make_vec_env` (the ``dinerdash[sb3]`` extra),
an SB3 ``VecEnv`` over one :class:`~dinerdash.DinerDashVectorEnv` (one Step call per server per
step, where SB3's ``DummyVecEnv`` makes one per environment) that speaks SB3's conventions
(docs/client.md#training-with-stable-baselines3).
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import gymnasium as gym
import numpy as np
from gymnasium.vector import AutoresetMode

try:
    from stable_baselines3.common.vec_env import VecEnv, VecMonitor
    from stable_baselines3.common.vec_env.base_vec_env import VecEnvIndices
except ImportError as e:  # pragma: no cover - depends on the installed extras
    raise ImportError("dinerdash.sb3 needs stable-baselines3: pip install 'dinerdash[sb3]'") from e

from .vector import DinerDashVectorEnv

__all__ = ["DinerDashSB3VecEnv", "make_vec_env"]


class DinerDashSB3VecEnv(VecEnv):
    """An SB3 ``VecEnv`` over one :class:`~dinerdash.DinerDashVectorEnv` (autoreset SAME_STEP).

    ``get_attr`` reads an attribute of the vector env (the same value for every environment);
    ``env_method`` knows ``action_masks`` (one ``(57,)`` mask per environment) and ``render``.
    """

    #: The methods ``env_method`` can call: each returns one value per environment.
    METHODS = ("action_masks", "render")

    def __init__(self, venv: DinerDashVectorEnv) -> None:
        if venv.autoreset_mode != AutoresetMode.SAME_STEP:
            raise ValueError(
                "DinerDashSB3VecEnv needs a vector env with autoreset_mode SAME_STEP (SB3's "
                f"convention), got {venv.autoreset_mode}"
            )
        self.venv = venv
        self._actions: np.ndarray | None = None
        super().__init__(venv.num_envs, venv.single_observation_space, venv.single_action_space)

    # -- VecEnv API -----------------------------------------------------------------------------

    def reset(self) -> np.ndarray:
        seeds = self._seeds
        seed: list[int] | None = None
        if any(s is not None for s in seeds):
            if any(s is None for s in seeds):
                raise ValueError("seed: give every environment a seed (VecEnv.seed does)")
            seed = [int(s) for s in seeds]
        options = self._options
        if any(options):
            if any(o != options[0] for o in options):
                raise ValueError(
                    "set_options: the environments of one batched session take the same "
                    "options (give per-environment arrivals as options['arrivals'], N lists)"
                )
            option = dict(options[0])
        else:
            option = None
        obs, info = self.venv.reset(seed=seed, options=option)
        self._reset_seeds()
        self._reset_options()
        self.reset_infos = _per_env(info, self.num_envs)
        return obs

    def step_async(self, actions: np.ndarray) -> None:
        self._actions = actions

    def step_wait(self) -> tuple[np.ndarray, np.ndarray, np.ndarray, list[dict[str, Any]]]:
        if self._actions is None:
            raise RuntimeError("step_wait() without step_async()")
        actions, self._actions = self._actions, None
        obs, rewards, terminated, truncated, info = self.venv.step(actions)
        dones = terminated | truncated
        infos: list[dict[str, Any]] = [{} for _ in range(self.num_envs)]
        if dones.any():
            final_obs = info["final_obs"]
            for i in np.flatnonzero(dones):
                infos[i]["terminal_observation"] = final_obs[i]
                infos[i]["TimeLimit.truncated"] = bool(truncated[i] and not terminated[i])
        if "reconnected" in info:
            for i in np.flatnonzero(info["reconnected"]):
                infos[i]["reconnected"] = True
        return obs, rewards.astype(np.float32), dones, infos

    def close(self) -> None:
        self.venv.close()

    def get_images(self) -> Sequence[np.ndarray | None]:
        if self.venv.render_mode != "rgb_array":
            return [None] * self.num_envs
        return list(self.venv.render() or ())

    def get_attr(self, attr_name: str, indices: VecEnvIndices = None) -> list[Any]:
        value = getattr(self.venv, attr_name)  # AttributeError when absent, as SB3 expects
        return [value for _ in self._get_indices(indices)]

    def set_attr(self, attr_name: str, value: Any, indices: VecEnvIndices = None) -> None:
        raise NotImplementedError(
            "the environments share one batched session: set attributes on the vector env "
            "(DinerDashSB3VecEnv.venv) instead"
        )

    def env_method(
        self,
        method_name: str,
        *method_args: Any,
        indices: VecEnvIndices = None,
        **method_kwargs: Any,
    ) -> list[Any]:
        if method_name not in self.METHODS:
            raise AttributeError(
                f"env_method: {method_name!r} is not one of {list(self.METHODS)} (the "
                "environments share one batched session)"
            )
        values = getattr(self.venv, method_name)(*method_args, **method_kwargs)
        return [values[i] for i in self._get_indices(indices)]

    def env_is_wrapped(
        self, wrapper_class: type[gym.Wrapper], indices: VecEnvIndices = None
    ) -> list[bool]:
        return [False for _ in self._get_indices(indices)]

    # -- extras ---------------------------------------------------------------------------------

    def action_masks(self) -> np.ndarray:
        """``(N, 57) bool``: the masks of every environment at once."""
        return self.venv.action_masks()


def _per_env(info: dict[str, Any], n: int) -> list[dict[str, Any]]:
    """A Gymnasium vector info (arrays with ``_key`` masks) as SB3's list of per-env dicts."""
    out: list[dict[str, Any]] = [{} for _ in range(n)]
    for key, value in info.items():
        if key.startswith("_") or not isinstance(value, np.ndarray) or len(value) != n:
            continue
        present = info.get(f"_{key}")
        for i in range(n):
            if present is None or present[i]:
                out[i][key] = value[i]
    return out


def make_vec_env(
    num_envs: int,
    address: str | Sequence[str] | None = None,
    *,
    monitor: bool = True,
    **env_kwargs: Any,
) -> VecEnv:
    """An SB3 ``VecEnv`` of ``num_envs`` environments in one batched session per server:
    ``address`` and ``env_kwargs`` are :class:`~dinerdash.DinerDashVectorEnv`'s, the autoreset
    mode SB3's (SAME_STEP); with ``monitor``, wrapped in SB3's ``VecMonitor``."""
    if "autoreset_mode" in env_kwargs:
        raise TypeError("make_vec_env: the autoreset mode is SB3's (SAME_STEP); do not pass one")
    venv = DinerDashVectorEnv(
        num_envs, address, autoreset_mode=AutoresetMode.SAME_STEP, **env_kwargs
    )
    try:
        env: VecEnv = DinerDashSB3VecEnv(venv)
    except BaseException:
        venv.close()
        raise
    return VecMonitor(env) if monitor else env

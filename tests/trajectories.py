"""Recording a vector env's trajectory and comparing two of them exactly: what the scale-out
and pipelining tests share."""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
from dinerdash import DinerDashVectorEnv
from gymnasium.vector import AutoresetMode

STEPS = 300

Step = Callable[[DinerDashVectorEnv, np.ndarray], tuple]


def plain_step(envs: DinerDashVectorEnv, actions: np.ndarray) -> tuple:
    return envs.step(actions)


def async_step(envs: DinerDashVectorEnv, actions: np.ndarray) -> tuple:
    envs.step_async(actions)
    return envs.step_wait()


def trajectory(envs: DinerDashVectorEnv, steps: int = STEPS, step: Step = plain_step) -> list:
    """Every reset and step of ``steps`` steps from seed 50, the actions mixing the expert's
    (the env needs ``expert=True``) with random ones, invalid ones included; in DISABLED mode the
    finished environments are reset through a ``reset_mask``."""
    rng = np.random.default_rng(3)
    out = [envs.reset(seed=50)]
    info = out[0][1]
    for _ in range(steps):
        actions = np.where(
            rng.random(envs.num_envs) < 0.6,
            info["expert_action"],
            rng.integers(0, 57, envs.num_envs),
        )
        out.append(step(envs, actions))
        info = out[-1][4]
        done = out[-1][2] | out[-1][3]
        if envs.autoreset_mode == AutoresetMode.DISABLED and done.any():
            out.append(envs.reset(seed=int(rng.integers(0, 1000)), options={"reset_mask": done}))
            info = out[-1][1]
    return out


def assert_same(a: list, b: list) -> None:
    """Two trajectories are equal, value for value (infos, ``final_obs`` and dtypes included)."""

    def eq(x, y, where):
        if isinstance(x, dict):
            assert x.keys() == y.keys(), where
            for k in x:
                eq(x[k], y[k], f"{where}.{k}")
        elif isinstance(x, np.ndarray) and x.dtype == object:
            for u, v in zip(x, y, strict=True):
                eq(u, v, where)
        elif x is None:
            assert y is None, where
        else:
            assert np.asarray(x).dtype == np.asarray(y).dtype, where
            np.testing.assert_array_equal(x, y, err_msg=where)

    assert len(a) == len(b)
    for t, (x, y) in enumerate(zip(a, b, strict=True)):
        for i, (u, v) in enumerate(zip(x, y, strict=True)):
            eq(u, v, f"step {t} item {i}")

"""GAIL: masked PPO whose reward comes from a discriminator instead of the game.

The discriminator ``D(s, a)`` (an MLP over the scaled observation and the action one-hot) is
trained each iteration, with the logistic loss, to tell the demonstrations' (observation, action)
pairs (label 1) from the policy's own of that iteration (label 0). The policy is rewarded
``-log(1 - D(s, a))``: the more a step looks like the expert's, the more it earns. The game's
score is only watched (the learning curve), never learned from.
"""

from __future__ import annotations

from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optax
from dinerdash.game import NUM_ACTIONS, OBSERVATION_SIZE

from . import ppo
from .demos import Demos
from .ppo import PPOConfig, Rollout, Trainer, observation_scale

__all__ = ["Discriminator", "GAILTrainer", "discriminator_loss", "fit_discriminator"]

#: Discriminator: hidden width, Adam steps per iteration, minibatch size, learning rate.
HIDDEN = 128
STEPS_PER_ITERATION = 8
BATCH = 1024
LEARNING_RATE = 3e-4


class Discriminator(eqx.Module):
    """(observation, action) -> logit of "an expert's step"."""

    layers: list[eqx.nn.Linear]
    #: What the observation is divided by: its upper bounds, as the policy's
    #: (:func:`~dinerdash_agents.ppo.observation_scale`).
    scale: tuple[float, ...] = eqx.field(static=True)

    def __init__(
        self, key: jax.Array, hidden: int = HIDDEN, scale: tuple[float, ...] | None = None
    ) -> None:
        k = jax.random.split(key, 3)
        self.scale = scale if scale is not None else observation_scale(PPOConfig())
        n_in = OBSERVATION_SIZE + NUM_ACTIONS
        self.layers = [
            eqx.nn.Linear(n_in, hidden, key=k[0]),
            eqx.nn.Linear(hidden, hidden, key=k[1]),
            eqx.nn.Linear(hidden, 1, key=k[2]),
        ]

    def __call__(self, obs: jax.Array, actions: jax.Array) -> jax.Array:
        scaled = obs / jnp.asarray(self.scale, jnp.float32)
        x = jnp.concatenate([scaled, jax.nn.one_hot(actions, NUM_ACTIONS)], -1)
        for layer in self.layers[:-1]:
            x = jnp.tanh(x @ layer.weight.T + layer.bias)
        last = self.layers[-1]
        return (x @ last.weight.T + last.bias)[:, 0]


def discriminator_loss(d: Discriminator, expert: dict, policy: dict) -> jax.Array:
    """Logistic loss: expert pairs labelled 1, the policy's labelled 0."""
    e = d(expert["obs"], expert["actions"])
    p = d(policy["obs"], policy["actions"])
    return jnp.mean(jax.nn.softplus(-e)) + jnp.mean(jax.nn.softplus(p))


def make_fit(optimizer: optax.GradientTransformation):
    @eqx.filter_jit
    def fit(d: Discriminator, opt_state: Any, expert: dict, policy: dict):
        """Adam steps over stacked minibatches (leading axis = steps)."""
        params, static = eqx.partition(d, eqx.is_array)

        def step(carry, parts):
            params, opt_state = carry
            e, p = parts
            loss, grads = jax.value_and_grad(
                lambda q: discriminator_loss(eqx.combine(q, static), e, p)
            )(params)
            updates, opt_state = optimizer.update(grads, opt_state, params)
            return (eqx.apply_updates(params, updates), opt_state), loss

        (params, opt_state), losses = jax.lax.scan(step, (params, opt_state), (expert, policy))
        return eqx.combine(params, static), opt_state, losses.mean()

    return fit


def fit_discriminator(
    d: Discriminator,
    expert: dict[str, np.ndarray],
    policy: dict[str, np.ndarray],
    *,
    steps: int,
    seed: int = 0,
) -> tuple[Discriminator, float]:
    """``steps`` Adam steps of :func:`discriminator_loss` on minibatches drawn from the two
    sets (for tests and one-off fits); returns the discriminator and its last mean loss."""
    optimizer = optax.adam(LEARNING_RATE)
    opt_state = optimizer.init(eqx.filter(d, eqx.is_array))
    fit = make_fit(optimizer)
    rng = np.random.default_rng(seed)
    e, p = _minibatches(rng, expert, policy, steps)
    d, _, loss = fit(d, opt_state, e, p)
    return d, float(loss)


def _minibatches(rng: np.random.Generator, expert: dict, policy: dict, steps: int):
    n = min(BATCH, len(policy["actions"]), len(expert["actions"]))

    def draw(data: dict) -> dict:
        idx = rng.integers(0, len(data["actions"]), size=(steps, n))
        return {k: v[idx] for k, v in data.items()}

    return draw(expert), draw(policy)


class GAILTrainer(Trainer):
    """Masked PPO rewarded by a discriminator trained against the demonstrations."""

    def __init__(
        self, config: PPOConfig, total_steps: int, seed: int = 0, demos: Demos | None = None
    ) -> None:
        super().__init__(config, total_steps, seed)
        if demos is None:
            raise ValueError("GAIL needs demonstrations")
        self.expert = {"obs": demos.observations, "actions": demos.actions.astype(np.int32)}
        self.discriminator = Discriminator(
            jax.random.PRNGKey(seed + 2), scale=observation_scale(config)
        )
        self._d_optimizer = optax.adam(LEARNING_RATE)
        self.d_opt_state = self._d_optimizer.init(eqx.filter(self.discriminator, eqx.is_array))
        self._fit = make_fit(self._d_optimizer)
        self._rng = np.random.default_rng(seed + 3)
        self._reward = eqx.filter_jit(lambda d, o, a: jax.nn.softplus(d(o, a)))

    def rewards_of(self, rollout: Rollout) -> np.ndarray:
        policy = {
            "obs": rollout.obs.reshape(-1, OBSERVATION_SIZE),
            "actions": rollout.actions.reshape(-1),
        }
        e, p = _minibatches(self._rng, self.expert, policy, STEPS_PER_ITERATION)
        self.discriminator, self.d_opt_state, _ = self._fit(
            self.discriminator, self.d_opt_state, e, p
        )
        reward = self._reward(self.discriminator, policy["obs"], policy["actions"])
        return np.asarray(reward).reshape(rollout.actions.shape)

    def state(self) -> dict[str, Any]:
        return {
            **super().state(),
            "discriminator": self.discriminator,
            "d_opt_state": self.d_opt_state,
        }

    def restore(self, model: Any, state: dict[str, Any], description: dict) -> None:
        super().restore(model, state, description)
        self.discriminator, self.d_opt_state = state["discriminator"], state["d_opt_state"]


# GAIL's policy is PPO's model (the discriminator stays in the trainer's state).
#: What :func:`~dinerdash_agents.checkpoint.load` needs of a ``gail`` checkpoint: PPO's model.
CHECKPOINT = ppo.CHECKPOINT

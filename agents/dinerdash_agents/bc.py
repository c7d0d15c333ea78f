"""Behaviour cloning as the paper has it: two fully connected layers with dropout between them,
trained with cross-entropy on the expert's action.

Two loss variants: ``masked`` (the default) takes the softmax over the legal actions of each
step only; ``plain`` (the paper's) over all 57. Plain cross-entropy spends much of its capacity
on "wait", the only legal action in a large share of expert steps.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import asdict, dataclass, replace

import equinox as eqx
import jax
from dinerdash.game import NUM_ACTIONS, OBSERVATION_HIGH, OBSERVATION_SIZE

from . import checkpoint
from .demos import Demos
from .supervised import cross_entropy, fit

__all__ = ["BCConfig", "BehaviourCloning", "init", "train"]


@dataclass(frozen=True)
class BCConfig:
    hidden: int = 512
    dropout: float = 0.2
    loss: str = "masked"  # "masked" | "plain"
    epochs: int = 10
    batch_size: int = 512
    learning_rate: float = 1e-3

    def to_json(self) -> dict:
        return asdict(self)

    @property
    def total_epochs(self) -> int:
        return self.epochs

    def with_epochs(self, epochs: int) -> BCConfig:
        """This config with ``epochs`` epochs."""
        return replace(self, epochs=epochs)


class BehaviourCloning(eqx.Module):
    """observation (40) -> FC hidden -> ReLU -> dropout -> FC 57 action logits."""

    hidden: eqx.nn.Linear
    dropout: eqx.nn.Dropout
    out: eqx.nn.Linear

    def __init__(self, config: BCConfig, key: jax.Array) -> None:
        k1, k2 = jax.random.split(key)
        self.hidden = eqx.nn.Linear(OBSERVATION_SIZE, config.hidden, key=k1)
        self.dropout = eqx.nn.Dropout(config.dropout)
        self.out = eqx.nn.Linear(config.hidden, NUM_ACTIONS, key=k2)

    def __call__(
        self, obs: jax.Array, mask: jax.Array | None = None, key: jax.Array | None = None
    ) -> jax.Array:
        """Action logits of a batch (B, 40); dropout is active only when ``key`` is given. The
        mask is not an input of BC (it only restricts the softmax)."""
        del mask
        # Scaled into [-1/6, 1] by the observation's upper bounds. Demonstrations carry no
        # server Spec: the bounds are ruleset v0's.
        x = obs / OBSERVATION_HIGH
        h = jax.nn.relu(jax.vmap(self.hidden)(x))
        h = self.dropout(h, key=key, inference=key is None)
        return jax.vmap(self.out)(h)


def init(config: BCConfig, seed: int = 0) -> BehaviourCloning:
    return BehaviourCloning(config, jax.random.PRNGKey(seed))


def train(
    demos: Demos,
    config: BCConfig,
    *,
    seed: int = 0,
    on_epoch: Callable[[str, int, float], None] | None = None,
) -> tuple[BehaviourCloning, dict]:
    """A BC network fitted to ``demos``; returns it and the per-epoch losses."""
    model = init(config, seed)
    use_mask = config.loss == "masked"

    def loss_fn(model, batch, key):
        logits = model(batch["obs"], key=key)
        return cross_entropy(logits, batch["action"], batch["mask"] if use_mask else None)

    data = {"obs": demos.observations, "action": demos.actions, "mask": demos.action_masks}
    model, losses = fit(
        model,
        loss_fn,
        data,
        epochs=config.epochs,
        batch_size=config.batch_size,
        learning_rate=config.learning_rate,
        seed=seed,
        on_epoch=None if on_epoch is None else (lambda e, loss: on_epoch("bc", e, loss)),
    )
    return model, {"cross_entropy": losses}


def config_from_json(values: dict) -> BCConfig:
    return BCConfig(**values)


#: What :func:`~dinerdash_agents.checkpoint.load` needs of a ``bc`` checkpoint.
CHECKPOINT = checkpoint.Hooks(config_from_json=config_from_json, init=init)

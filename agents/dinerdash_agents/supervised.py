"""Supervised learning on demonstrations, what BC and DPGM share: the (masked) cross-entropy and
the minibatch loop; and :func:`masked_logits`, through which every policy (PPO's too) keeps to the
legal actions.

The loop runs one whole epoch as a single jitted ``lax.scan`` over shuffled minibatches, so a
small network trains at the speed of XLA rather than of Python; the epoch is compiled once per
(loss, batch shape) and reused by every later epoch.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optax

__all__ = ["ILLEGAL_LOGIT", "cross_entropy", "fit", "masked_logits"]

#: The logit an illegal action gets: finite, so its gradient is 0 rather than NaN.
ILLEGAL_LOGIT = -1e9


def masked_logits(logits: jax.Array, mask: jax.Array | None) -> jax.Array:
    """``logits`` with every illegal action (``mask`` false) pushed to :data:`ILLEGAL_LOGIT`."""
    if mask is None:
        return logits
    return jnp.where(mask, logits, ILLEGAL_LOGIT)


def cross_entropy(logits: jax.Array, actions: jax.Array, mask: jax.Array | None) -> jax.Array:
    """Mean cross-entropy of the expert's ``actions``; with ``mask`` the softmax runs over the
    legal actions only (the expert's action is always legal), without it over all 57."""
    logp = jax.nn.log_softmax(masked_logits(logits, mask), axis=-1)
    return -jnp.mean(jnp.take_along_axis(logp, actions[:, None], axis=-1))


def fit(
    model: Any,
    loss_fn: Callable[[Any, dict[str, jax.Array], jax.Array], jax.Array],
    data: dict[str, np.ndarray],
    *,
    epochs: int,
    batch_size: int,
    learning_rate: float,
    seed: int,
    trainable: Callable[[Any], Any] | None = None,
    on_epoch: Callable[[int, float], None] | None = None,
) -> tuple[Any, list[float]]:
    """Adam on ``loss_fn(model, batch, key)`` over shuffled minibatches of ``data`` (arrays with
    one row per step) for ``epochs`` epochs; returns the model and the mean loss of each epoch.

    ``trainable(model)`` (default: every array) is a pytree of booleans saying which leaves
    learn; the others stay as they are (DPGM's stage 2 freezes its factor tables this way).
    """
    n = len(next(iter(data.values())))
    batch_size = max(1, min(batch_size, n))
    batches = n // batch_size  # the remainder of a shuffle is left for the next epoch
    spec = trainable(model) if trainable is not None else eqx.is_array
    params, static = eqx.partition(model, spec)
    optimizer = optax.adam(learning_rate)
    opt_state = optimizer.init(params)

    @eqx.filter_jit
    def epoch(params, opt_state, batched, key):
        def step(carry, inputs):
            params, opt_state = carry
            batch, k = inputs
            loss, grads = jax.value_and_grad(lambda p: loss_fn(eqx.combine(p, static), batch, k))(
                params
            )
            updates, opt_state = optimizer.update(grads, opt_state, params)
            return (eqx.apply_updates(params, updates), opt_state), loss

        keys = jax.random.split(key, batches)
        (params, opt_state), losses = jax.lax.scan(step, (params, opt_state), (batched, keys))
        return params, opt_state, jnp.mean(losses)

    rng = np.random.default_rng(seed)
    key = jax.random.PRNGKey(seed)
    history: list[float] = []
    for e in range(epochs):
        order = rng.permutation(n)[: batches * batch_size]
        batched = {
            name: jnp.asarray(a[order].reshape(batches, batch_size, *a.shape[1:]))
            for name, a in data.items()
        }
        key, sub = jax.random.split(key)
        params, opt_state, loss = epoch(params, opt_state, batched, sub)
        history.append(float(loss))
        if on_epoch is not None:
            on_epoch(e, history[-1])
    return eqx.combine(params, static), history

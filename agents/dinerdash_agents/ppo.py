"""PPO against batched server sessions: the model, the update and the :class:`Trainer`.

Not a CleanRL-style single file: the algorithm is a class, as Stable-Baselines3's are.
:class:`Trainer` holds one iteration (collect, then update) and five hooks its variants
override: :meth:`~Trainer.rewards_of` (GAIL's discriminator reward), :meth:`~Trainer.update_coefs`
with :func:`make_update`'s ``combine`` (kick-starting's pull toward a teacher),
:meth:`~Trainer.record_info` (the teacher's actions kept with each step),
:meth:`~Trainer.view` (a learner with memory sees its observations' features) and
:meth:`~Trainer.with_info` (a critic reads the groups lost). The run around it
(servers, checkpoints, curve, resume) is :mod:`~dinerdash_agents.train_rl`.

``gymnasium.make_vec("dinerdash:DinerDash-v0", num_envs=N, address=..., autoreset_mode=SAME_STEP)``
feeds a jitted actor-critic: per step one jitted call acts for the environments of a vector env;
per iteration one jitted call computes the advantages and runs every epoch and minibatch of the
update (a ``lax.scan``).

Pipelining: the trainer may play on several vector envs that together hold the N environments
(:meth:`Trainer.attach`; ``train --pipeline 2``: two halves). It sends one's step with
``step_async`` and acts for the other while the server steps the first, so that the server and
the trainer work at the same time. Environment ``i`` is seeded, and its actions drawn, exactly as
with one vector env: the samples, and so the algorithm, do not depend on the split.

- ``ppo-masked``: illegal actions (``info["action_mask"]``) get the logit
  :data:`~dinerdash_agents.supervised.ILLEGAL_LOGIT` when acting and in the update, so the policy
  never takes one and spends no probability on them.
- ``ppo``: the paper's PPO over all 57 actions; an illegal action only lets a tick pass.

The networks see the observation divided by its upper bounds, which the server sends in its Spec:
``PPOConfig.observation_high``, taken from the vector env's ``single_observation_space.high`` when
a run starts (:mod:`~dinerdash_agents.train_rl`) and kept in the checkpoint.

Termination and truncation differ in one place, the bootstrap: after a terminated episode the
next value is 0; after a truncated one it is the critic's value of the episode's last observation
(``info["final_obs"]``), not of the next episode's first. Either way the advantage stops at the
episode's end. Elsewhere the next value is the value of the next step's observation, which the
acting call computes anyway: only the truncated episodes' last observations, and the observations
after an iteration's last step, need a critic call of their own (one per iteration).
"""

from __future__ import annotations

import itertools
import time
from collections.abc import Callable, Sequence
from dataclasses import asdict, dataclass, replace
from functools import partial
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optax
from dinerdash.game import NUM_ACTIONS, OBSERVATION_HIGH, OBSERVATION_SIZE

from . import checkpoint
from .seeds import as_ranges, training_seeds
from .supervised import masked_logits

__all__ = ["ActorCritic", "PPOConfig", "gae", "init", "observation_scale", "sample_actions"]


@dataclass(frozen=True)
class PPOConfig:
    """PPO's hyper-parameters; the defaults are those of the committed results."""

    masked: bool = True
    num_envs: int = 256
    num_steps: int = 64
    hidden: int = 128
    learning_rate: float = 3e-4
    anneal_lr: bool = True
    gamma: float = 0.995
    gae_lambda: float = 0.95
    num_minibatches: int = 4
    update_epochs: int = 2
    clip_coef: float = 0.2
    ent_coef: float = 0.01
    vf_coef: float = 0.5
    max_grad_norm: float = 0.5
    #: Rewards are multiples of 10, and -500 for a group that runs away: scaled to about 1.
    reward_scale: float = 0.01
    #: Training episodes are truncated here (ruleset v0 has no time limit).
    max_episode_steps: int = 5000
    #: The observation's upper bounds the networks divide it by, from the server's Spec (the env's
    #: ``single_observation_space.high``); ``None`` (a checkpoint written before they were
    #: recorded): ruleset v0's, :data:`dinerdash.game.OBSERVATION_HIGH`.
    observation_high: tuple[float, ...] | None = None

    def __post_init__(self) -> None:
        for name, ok, allowed in (
            ("learning_rate", self.learning_rate > 0, "above 0"),
            ("gamma", 0 < self.gamma <= 1, "in (0, 1]"),
            ("gae_lambda", 0 <= self.gae_lambda <= 1, "in [0, 1]"),
            ("ent_coef", self.ent_coef >= 0, "0 or more"),
        ):
            if not ok:
                raise ValueError(f"{name} is {getattr(self, name)}; it must be {allowed}")
        if self.observation_high is not None:  # a list, read back from JSON
            high = tuple(float(x) for x in self.observation_high)
            if len(high) != OBSERVATION_SIZE:
                raise TypeError(
                    f"observation_high has {len(high)} bounds, expected {OBSERVATION_SIZE}"
                )
            object.__setattr__(self, "observation_high", high)

    def to_json(self) -> dict:
        return asdict(self)

    def for_num_envs(self, num_envs: int) -> PPOConfig:
        """This config for ``num_envs`` environments, adapted above :data:`BASE_ENVS` so that
        learning per environment step stays the same: the rollout shortened (``num_steps`` =
        64 · 256 / N, at least :data:`MIN_STEPS`) and the minibatches kept at the base's size
        (4,096 samples) by counting more of them, so the gradient steps per sample, their
        batch size and so the learning rate stay the base's. At 4,096 environments: 32 steps
        an iteration (131,072 samples), 32 minibatches. At or below :data:`BASE_ENVS` only
        ``num_envs`` changes."""
        if num_envs <= BASE_ENVS:
            return replace(self, num_envs=num_envs)
        minibatch = BASE_ENVS * self.num_steps // self.num_minibatches
        steps = max(MIN_STEPS, self.num_steps * BASE_ENVS // num_envs)
        minibatches = max(1, num_envs * steps // minibatch)
        return replace(self, num_envs=num_envs, num_steps=steps, num_minibatches=minibatches)


#: The environment count the default hyper-parameters were chosen at (256 × 64 steps, 4
#: minibatches of 4,096 samples); :meth:`PPOConfig.for_num_envs` adapts them above it.
BASE_ENVS = 256
#: The shortest rollout :meth:`PPOConfig.for_num_envs` gives: at 4,096 environments 16 steps
#: scored 3 % below the default at the same env steps, 32 the same (docs/agents.md).
MIN_STEPS = 32


def config_from_json(values: dict) -> PPOConfig:
    return PPOConfig(**values)


def _mlp(sizes: list[int], out_scale: float, key: jax.Array) -> list[eqx.nn.Linear]:
    """Linear layers with CleanRL's orthogonal initialisation (sqrt 2 inside, ``out_scale`` last)
    and zero biases."""
    keys = jax.random.split(key, len(sizes) - 1)
    layers = []
    for i, (n_in, n_out) in enumerate(itertools.pairwise(sizes)):
        scale = out_scale if i == len(sizes) - 2 else float(np.sqrt(2.0))
        w = jax.nn.initializers.orthogonal(scale)(keys[i], (n_out, n_in), jnp.float32)
        layer = eqx.nn.Linear(n_in, n_out, key=keys[i])
        layer = eqx.tree_at(lambda lin: (lin.weight, lin.bias), layer, (w, jnp.zeros(n_out)))
        layers.append(layer)
    return layers


def observation_scale(config: PPOConfig) -> tuple[float, ...]:
    """What the networks of ``config`` divide the observation by: its upper bounds."""
    if config.observation_high is not None:
        return config.observation_high
    return tuple(float(x) for x in OBSERVATION_HIGH)


def _forward(layers: list[eqx.nn.Linear], x: jax.Array) -> jax.Array:
    for layer in layers[:-1]:
        x = jnp.tanh(x @ layer.weight.T + layer.bias)
    return x @ layers[-1].weight.T + layers[-1].bias


class ActorCritic(eqx.Module):
    """Separate actor and critic MLPs (two tanh layers of ``hidden`` each) over the scaled
    observation. Calling it gives the actor's logits, as every agent of this package does."""

    actor: list[eqx.nn.Linear]
    critic: list[eqx.nn.Linear]
    #: :func:`observation_scale`: a constant of the model, not a parameter.
    scale: tuple[float, ...] = eqx.field(static=True)

    def __init__(self, config: PPOConfig, key: jax.Array) -> None:
        ka, kc = jax.random.split(key)
        h = config.hidden
        self.scale = observation_scale(config)
        self.actor = _mlp([OBSERVATION_SIZE, h, h, NUM_ACTIONS], 0.01, ka)
        self.critic = _mlp([OBSERVATION_SIZE, h, h, 1], 1.0, kc)

    def __call__(
        self, obs: jax.Array, mask: jax.Array | None = None, key: jax.Array | None = None
    ) -> jax.Array:
        """Action logits of a batch (B, 40); the mask only restricts the softmax."""
        del mask, key
        return _forward(self.actor, obs / jnp.asarray(self.scale, jnp.float32))

    def value(self, obs: jax.Array) -> jax.Array:
        """The critic's value of each observation of a batch, (B,)."""
        return _forward(self.critic, obs / jnp.asarray(self.scale, jnp.float32))[:, 0]


def init(config: PPOConfig, seed: int = 0) -> ActorCritic:
    return ActorCritic(config, jax.random.PRNGKey(seed))


def gae(
    rewards: jax.Array,
    values: jax.Array,
    next_values: jax.Array,
    terminated: jax.Array,
    done: jax.Array,
    gamma: float,
    lam: float,
) -> tuple[jax.Array, jax.Array]:
    """Generalised advantage estimates and returns of time-major ``(T, N)`` arrays.

    ``next_values[t]`` is the critic's value of what follows step ``t``: the next observation, or
    where the episode was truncated at ``t``, its last observation. ``terminated`` zeroes that
    bootstrap; ``done`` (terminated or truncated) keeps the advantage from running into the next
    episode.
    """

    def back(carry: jax.Array, x: tuple[jax.Array, ...]) -> tuple[jax.Array, jax.Array]:
        r, v, nv, term, d = x
        delta = r + gamma * (1.0 - term) * nv - v
        adv = delta + gamma * lam * (1.0 - d) * carry
        return adv, adv

    xs = (rewards, values, next_values, terminated, done)
    _, adv = jax.lax.scan(back, jnp.zeros_like(values[0]), xs, reverse=True)
    return adv, adv + values


def sample_actions(logits: jax.Array, u: jax.Array) -> tuple[jax.Array, jax.Array]:
    """One action per row of ``logits`` by inverse transform sampling with ``u`` (one uniform
    number in [0, 1) per row, drawn on the device by the acting call: far cheaper on a CPU than
    the 57 Gumbel draws per row of ``jax.random.categorical``), and its log-probability. An
    action of probability 0 (an illegal one, masked) is never picked: the pick is the first
    action whose cumulative probability exceeds ``u`` times the total, and an action of
    probability 0 adds nothing to it."""
    logp = jax.nn.log_softmax(logits)
    cdf = jnp.cumsum(jnp.exp(logp), axis=-1)
    target = u[:, None] * cdf[:, -1:]
    actions = jnp.minimum(jnp.sum(cdf <= target, axis=-1), logits.shape[-1] - 1)
    return actions, jnp.take_along_axis(logp, actions[:, None], axis=1)[:, 0]


def entropy(logits: jax.Array, mask: jax.Array | None) -> jax.Array:
    """Entropy of each row's distribution (over the legal actions only, with ``mask``)."""
    logp = jax.nn.log_softmax(logits)
    plogp = jnp.exp(logp) * logp
    if mask is not None:
        plogp = jnp.where(mask, plogp, 0.0)
    return -plogp.sum(-1)


def make_act(masked: bool, asynchronous: bool = False) -> Callable[..., jax.Array]:
    """The jitted acting call: ``act(leaves, key, t, obs, mask, treedef=..., rows=..., total=...)``.

    Everything happens on the device: the uniform numbers of step ``t`` are drawn there for all
    ``total`` environments of the trainer from the iteration's ``key`` (``fold_in(key, t)``) and
    the vector env's ``rows = (start, stop)`` taken, so a split into pipelined vector envs draws
    what one vector env would; then the policy's actions, their log-probabilities and the
    critic's values. The observations and masks (host arrays) cross to the device once, as the
    call's arguments (jit's own transfer: ~10x cheaper per call on a CPU than an explicit
    ``jax.device_put``), and come back as outputs, the device's copies, which the update takes
    (:func:`_assemble`); the caller copies the ``(3, B)`` result to the host once
    (``jax.device_get``). Returns ``(result, obs, mask)``.

    ``asynchronous``: the same computation inside a loop whose trip count (1) is an argument,
    ``act(leaves, key, t, obs, mask, np.int32(1), ...)``. XLA's CPU client runs a small
    loop-free program inline in the calling thread but hands one with a loop to its own
    threads: the call then returns at once, and the trainer decodes another vector env's step
    while the other core computes the actions (the results are bit for bit the same). On an
    accelerator every call is asynchronous anyway."""

    def compute(model, key, t, obs, mask, rows, total) -> jax.Array:
        u = jax.random.uniform(jax.random.fold_in(key, t), (total,))[rows[0] : rows[1]]
        logits = masked_logits(model(obs), mask if masked else None)
        actions, logp = sample_actions(logits, u)
        return jnp.stack([actions.astype(jnp.float32), logp, model.value(obs)])

    @partial(jax.jit, static_argnames=("treedef", "rows", "total"))
    def act(leaves, key, t, obs, mask, *, treedef, rows, total):
        """For the model ``jax.tree.unflatten(treedef, leaves)`` (its arrays passed as a list:
        cheaper to hand over than the module): sampled actions for ``obs``, their
        log-probabilities and the critic's values of ``obs``, stacked in one ``(3, B)`` array
        so that one copy brings them to the host (an action index is exact in float32)."""
        model = jax.tree.unflatten(treedef, leaves)
        return compute(model, key, t, obs, mask, rows, total), obs, mask

    @partial(jax.jit, static_argnames=("treedef", "rows", "total"))
    def act_async(leaves, key, t, obs, mask, once, *, treedef, rows, total):
        model = jax.tree.unflatten(treedef, leaves)
        out = jnp.zeros((3, obs.shape[0]), jnp.float32)
        step = lambda _, __: compute(model, key, t, obs, mask, rows, total)  # noqa: E731
        return jax.lax.fori_loop(0, once, step, out), obs, mask

    return act_async if asynchronous else act


@jax.jit
def _assemble(steps: list[list[tuple[jax.Array, ...]]]) -> dict[str, jax.Array]:
    """The device's copies of an iteration's steps (per step, per vector env: observations,
    masks, the acting call's ``(3, B)`` output) as time-major ``(T, N, ...)`` arrays, on the
    device: one call, no copy through the host."""

    def joined(k: int, axis: int = 0) -> jax.Array:
        return jnp.stack([jnp.concatenate([g[k] for g in step], axis=axis) for step in steps])

    out = joined(2, axis=1)  # (T, 3, N)
    return {
        "obs": joined(0),
        "mask": joined(1),
        "actions": out[:, 0].astype(jnp.int32),
        "logp": out[:, 1],
        "values": out[:, 2],
    }


@jax.jit
def _values(model: ActorCritic, obs: jax.Array) -> jax.Array:
    return model.value(obs)


#: The rollout's arrays that only the advantages are computed from; the update minibatches the
#: others (and the advantages and returns).
GAE_INPUTS = ("rewards", "values", "next_values", "terminated", "done")


#: ``combine(terms, mb, logits, coefs) -> (loss, extra statistics)``: how :func:`make_update`
#: adds up the loss terms of a minibatch (``terms``: ``policy_loss``, ``value_loss``,
#: ``entropy``); ``coefs`` is what the update was called with. Kick-starting adds its own.
LossCombiner = Callable[..., tuple[jax.Array, dict[str, jax.Array]]]


def make_update(
    config: PPOConfig,
    optimizer: optax.GradientTransformation,
    combine: LossCombiner | None = None,
) -> Callable[..., tuple[Any, Any, dict[str, jax.Array]]]:
    def loss_fn(model: ActorCritic, mb: dict[str, jax.Array], coefs: Any = None):
        mask = mb["mask"] if config.masked else None
        logits = masked_logits(model(mb["obs"]), mask)
        logp = jnp.take_along_axis(jax.nn.log_softmax(logits), mb["actions"][:, None], axis=1)
        log_ratio = logp[:, 0] - mb["logp"]
        ratio = jnp.exp(log_ratio)
        adv = (mb["adv"] - mb["adv"].mean()) / (mb["adv"].std() + 1e-8)
        clipped = jnp.clip(ratio, 1 - config.clip_coef, 1 + config.clip_coef)
        pg = jnp.maximum(-adv * ratio, -adv * clipped).mean()
        v_loss = 0.5 * ((model.value(mb["obs"]) - mb["returns"]) ** 2).mean()
        ent = entropy(logits, mask).mean()
        kl = ((ratio - 1) - log_ratio).mean()
        stats = {"policy_loss": pg, "value_loss": v_loss, "entropy": ent, "approx_kl": kl}
        if combine is None:
            loss = pg + config.vf_coef * v_loss - config.ent_coef * ent
            return loss, stats
        loss, extra = combine(stats, mb, logits, coefs)
        return loss, {**stats, **extra}

    @eqx.filter_jit
    def update(
        model: ActorCritic,
        opt_state: Any,
        rollout: dict[str, jax.Array],
        key: jax.Array,
        coefs: Any = None,
    ):
        """GAE over the iteration's time-major ``(T, N, ...)`` arrays (:meth:`Rollout.batch`),
        then every epoch and minibatch of one PPO update over its ``T * N`` samples; returns
        the model, the optimiser state and the mean of each statistic. ``coefs`` (arrays) go to
        the ``combine`` of :func:`make_update`."""
        adv, returns = gae(
            *(rollout[k] for k in GAE_INPUTS), gamma=config.gamma, lam=config.gae_lambda
        )
        batch = {k: v for k, v in rollout.items() if k not in GAE_INPUTS}
        batch = {**batch, "adv": adv, "returns": returns}
        batch = jax.tree.map(lambda a: a.reshape(-1, *a.shape[2:]), batch)
        size = batch["obs"].shape[0]
        mb = size // config.num_minibatches
        params, static = eqx.partition(model, eqx.is_array)

        def epoch(carry, k):
            def minibatch(carry, part):
                params, opt_state = carry
                grads, stats = jax.grad(
                    lambda p: loss_fn(eqx.combine(p, static), part, coefs), has_aux=True
                )(params)
                updates, opt_state = optimizer.update(grads, opt_state, params)
                return (eqx.apply_updates(params, updates), opt_state), stats

            order = jax.random.permutation(k, size)[: mb * config.num_minibatches]
            parts = jax.tree.map(
                lambda x: x[order].reshape(config.num_minibatches, mb, *x.shape[1:]), batch
            )
            return jax.lax.scan(minibatch, carry, parts)

        keys = jax.random.split(key, config.update_epochs)
        (params, opt_state), stats = jax.lax.scan(epoch, (params, opt_state), keys)
        return eqx.combine(params, static), opt_state, jax.tree.map(jnp.mean, stats)

    return update


def optimizer_for(config: PPOConfig, iterations: int) -> optax.GradientTransformation:
    """Adam with CleanRL's clipping; the learning rate falls linearly to 0 over ``iterations``
    when annealed."""
    updates = iterations * config.update_epochs * config.num_minibatches
    lr = (
        optax.linear_schedule(config.learning_rate, 0.0, max(updates, 1))
        if config.anneal_lr
        else config.learning_rate
    )
    return optax.chain(optax.clip_by_global_norm(config.max_grad_norm), optax.adam(lr, eps=1e-5))


advantages = jax.jit(gae, static_argnames=("gamma", "lam"))

#: The parts of an iteration :attr:`Trainer.timings` holds.
TIMED = ("act", "env", "bootstrap", "collect", "update")


class Rollout:
    """Time-major buffers of one iteration: ``num_steps`` steps of ``num_envs`` environments."""

    def __init__(
        self, steps: int, envs: int, expert: bool = False, width: int = OBSERVATION_SIZE
    ) -> None:
        #: With ``expert``: the teacher's action of each step (``info["expert_action"]`` of the
        #: observation acted on), for kick-starting.
        self.expert_actions = np.zeros((steps, envs), np.int32) if expert else None
        #: The model's inputs: the observations, with a learner's memory features beside them
        #: when ``width`` is wider (:meth:`Trainer.view`).
        self.obs = np.zeros((steps, envs, width), np.float32)
        self.mask = np.zeros((steps, envs, NUM_ACTIONS), np.bool_)
        self.actions = np.zeros((steps, envs), np.int32)
        self.logp = np.zeros((steps, envs), np.float32)
        self.values = np.zeros((steps, envs), np.float32)
        self.next_values = np.zeros((steps, envs), np.float32)
        self.rewards = np.zeros((steps, envs), np.float32)
        self.terminated = np.zeros((steps, envs), np.float32)
        self.done = np.zeros((steps, envs), np.float32)
        #: The same ``obs``, ``mask``, ``actions``, ``logp`` and ``values`` as the device holds
        #: them (:func:`_assemble`), set by :meth:`Trainer.collect`: the update takes these, so
        #: the observations cross to the device once, when acted on.
        self.device: dict[str, jax.Array] | None = None

    def batch(self, rewards: np.ndarray) -> dict[str, Any]:
        """The iteration's arrays, time-major, as the update takes them (it computes the
        advantages from ``rewards``, the rewards learnt from, and the :data:`GAE_INPUTS`, and
        minibatches the others)."""
        batch = {
            "obs": self.obs,
            "mask": self.mask,
            "actions": self.actions,
            "logp": self.logp,
            "rewards": rewards,
            "values": self.values,
            "next_values": self.next_values,
            "terminated": self.terminated,
            "done": self.done,
        }
        if self.expert_actions is not None:
            batch["expert_actions"] = self.expert_actions
        if self.device is not None:
            batch.update(self.device)
        return batch


class _Group:
    """One vector env of the trainer's: the environments ``rows`` of the buffers, their current
    observations and masks, and the step sent to the server and not yet received."""

    def __init__(self, envs: Any, rows: slice) -> None:
        self.envs, self.rows = envs, rows
        #: The current observations (as the model sees them), masks and infos of the group's
        #: environments.
        self.obs: np.ndarray = np.zeros(0)
        self.mask: np.ndarray = np.zeros(0)
        self.info: dict[str, Any] = {}
        #: The step under way: ``True`` after ``step_async``, or the results of a blocking step;
        #: and its index in the iteration.
        self.sent: Any = None
        self.step = 0
        #: The group's own ``obs -> model input`` (:meth:`Trainer.view`), or ``None``; one with
        #: an ``acted(actions)`` method is told the actions sent.
        self.view: Callable[[np.ndarray], np.ndarray] | None = None

    def see(self, obs: np.ndarray) -> np.ndarray:
        return obs if self.view is None else self.view(obs)


class Trainer:
    """PPO's state between iterations (model, optimiser, random key, counts, learning curve) and
    one iteration: collect ``num_steps`` steps of every environment, then update.

    Its variants subclass it and override its five hooks: GAIL replaces :meth:`rewards_of`;
    kick-starting adds a loss term through :meth:`update_coefs` and :func:`make_update`'s
    ``combine``, and keeps the teacher's actions through :meth:`record_info`; a learner with
    memory sees its observations through :meth:`view`; a critic reads more of each step's info
    through :meth:`with_info`.
    """

    def __init__(self, config: PPOConfig, total_steps: int, seed: int = 0) -> None:
        self.config = config
        self.total_steps = int(total_steps)
        self.seed = seed
        self.per_iteration = config.num_envs * config.num_steps
        #: Whole iterations, enough to reach ``total_steps``.
        self.iterations = max(-(-self.total_steps // self.per_iteration), 1)
        self.model = init(config, seed)
        self.optimizer = optimizer_for(config, self.iterations)
        self.opt_state = self.optimizer.init(eqx.filter(self.model, eqx.is_array))
        self.key = jax.random.PRNGKey(seed + 1)
        #: What each iteration's acting key is folded from (:meth:`_iteration_key`).
        self._acting_key = jax.random.PRNGKey(seed + 2)
        #: Environment steps and iterations done, episodes ended.
        self.steps = 0
        self.iteration = 0
        self.episodes = 0
        #: One row per iteration: steps, mean score of the last 100 episodes, env-steps/s.
        self.curve: list[tuple[int, float, float]] = []
        self.recent_scores: list[float] = []
        #: The seeds trained on, as ``[first, last]`` runs (the checkpoint's
        #: ``data["seed_ranges"]``): the environments' first resets (:meth:`attach`), and what
        #: the run adds (demonstrations, a starting checkpoint's).
        self.seed_ranges: list[list[int]] = []
        #: The lengths of the same episodes (not checkpointed: a resumed run starts it afresh).
        self.recent_lengths: list[int] = []
        #: Seconds spent since the trainer was made, by part of the iteration: ``act`` (the
        #: jitted acting calls, copies included), ``env`` (waiting for the environments' steps,
        #: the client's decoding included), ``bootstrap`` (the values of the truncated episodes'
        #: last observations), ``collect`` (the whole of :meth:`collect`), ``update`` (the
        #: rewards learnt from, the advantages and the update, until its results are there).
        self.timings = dict.fromkeys(TIMED, 0.0)
        self._act = make_act(config.masked)
        self._act_async = make_act(config.masked, asynchronous=True)
        self._once = np.int32(1)
        #: The model's arrays and structure as the acting calls of an iteration take them.
        self._leaves, self._treedef = jax.tree.flatten(self.model)
        self._update = make_update(config, self.optimizer)
        self._buffers = Rollout(config.num_steps, config.num_envs)
        self._envs: Any = None
        self._groups: list[_Group] = []
        #: The truncated episodes of this iteration: (step, environment, last observation).
        self._truncations: list[tuple[int, int, np.ndarray]] = []
        #: Per step and vector env of the iteration: the device's observations, masks and acting
        #: output, which the update takes (:func:`_assemble`).
        self._on_device: list[list[Any]] = []

    # --- the environments ------------------------------------------------------------------

    def attach(self, envs: Any) -> None:
        """Starts playing on ``envs``: a SAME_STEP vector env of ``num_envs`` environments, or a
        sequence of them that hold ``num_envs`` in all (environment ``i`` of the trainer is then
        the ``i``-th counting across them in order; with several, their steps are pipelined).
        Environment ``i`` is seeded at the first reset with the ``i``-th seed from ``seed *
        num_envs + steps`` on (a resumed run's ``steps`` are those done) that is not one of
        :data:`~dinerdash_agents.seeds.RESERVED_SEEDS`, and the seeds are added to
        :attr:`seed_ranges`."""
        several = isinstance(envs, Sequence)
        parts = list(envs) if several else [envs]
        sizes = [e.num_envs for e in parts]
        if sum(sizes) != self.config.num_envs:
            raise ValueError(
                f"the vector envs hold {sum(sizes)} environments ({sizes}); the config has "
                f"num_envs={self.config.num_envs}"
            )
        self._envs = envs
        self._groups, start = [], 0
        seeds = training_seeds(self.seed * self.config.num_envs + self.steps, sum(sizes))
        self.seed_ranges = as_ranges(self.seeds_trained_on() + seeds)
        for part, size in zip(parts, sizes, strict=True):
            group = _Group(part, slice(start, start + size))
            group.view = self.view()
            obs, info = part.reset(seed=seeds[start : start + size])
            group.obs = self.with_info(group.see(obs), info)
            group.mask, group.info = info["action_mask"], info
            self._groups.append(group)
            start += size
        self._score = np.zeros(self.config.num_envs)
        self._length = np.zeros(self.config.num_envs, np.int64)

    def _next_key(self) -> jax.Array:
        self.key, k = jax.random.split(self.key)
        return k

    def collect(self) -> Rollout:
        """Plays ``num_steps`` steps of every environment into the buffers.

        With several vector envs, one's step is on the server and its decoding under way while
        the actions of the next are computed: the acting order is step 0 of every vector env in
        turn, then step 1, ...; a vector env's step is received just before the next one's
        actions are sent."""
        began = time.perf_counter()
        # The iteration's own stream, so that a resumed run draws what the original would have;
        # on the device, as the acting calls draw from it.
        key = self._iteration_key()
        self._leaves, self._treedef = jax.tree.flatten(self.model)
        groups, steps = self._groups, self.config.num_steps
        self._truncations = []
        self._on_device = [[None] * len(groups) for _ in range(steps)]
        if len(groups) == 1:
            (group,) = groups
            for t in range(steps):
                began_act = time.perf_counter()
                acting = self._act(*self._inputs(group, key, t), **self._static(group))
                self.timings["act"] += time.perf_counter() - began_act
                self._send(group, t, acting)
                self._receive(group, t)
        else:
            turns = [(t, group) for t in range(steps) for group in groups]
            inputs = self._inputs(groups[0], key, 0)
            acting = self._act_async(*inputs, self._once, **self._static(groups[0]))
            for k, (t, group) in enumerate(turns):
                following = turns[k + 1] if k + 1 < len(turns) else None
                if following is not None and following[1].sent is not None:
                    self._receive(following[1], following[1].step)
                self._send(group, t, acting)
                if following is not None:
                    began_act = time.perf_counter()
                    inputs = self._inputs(following[1], key, following[0])
                    acting = self._act_async(*inputs, self._once, **self._static(following[1]))
                    self.timings["act"] += time.perf_counter() - began_act
            for group in groups:
                self._receive(group, steps - 1)
        self._bootstrap()
        self._buffers.device = _assemble(self._on_device)
        self.timings["collect"] += time.perf_counter() - began
        return self._buffers

    def _iteration_key(self) -> jax.Array:
        """The key the acting calls of this iteration draw from (on the device)."""
        iteration = jax.device_put(np.uint32(self.iteration))  # one explicit copy an iteration
        return jax.random.fold_in(self._acting_key, iteration)

    def _inputs(self, group: _Group, key: jax.Array, t: int) -> tuple[Any, ...]:
        """The acting call's inputs for ``group``'s step ``t``: its observations and masks,
        written into the rollout's buffers first, which the call copies to the device (and
        returns there, for the update). The buffers, not the vector env's arrays: on a CPU the
        device's copy may be the host's memory itself, and the buffers are not written again
        before the update that reads them has run."""
        b, rows = self._buffers, group.rows
        b.obs[t, rows], b.mask[t, rows] = group.obs, group.mask
        return self._leaves, key, np.int32(t), b.obs[t, rows], b.mask[t, rows]

    def _static(self, group: _Group) -> dict[str, Any]:
        return {
            "treedef": self._treedef,
            "rows": (group.rows.start, group.rows.stop),
            "total": self.config.num_envs,
        }

    def _send(self, group: _Group, t: int, acting: jax.Array) -> None:
        """Records ``group``'s step ``t`` (its observations, the actions of ``acting``, their
        log-probabilities and values) and sends the actions: a blocking step with one vector
        env, else ``step_async``."""
        b, rows, timings = self._buffers, group.rows, self.timings
        began = time.perf_counter()
        result, obs, mask = acting
        a_logp_v = jax.device_get(result)  # the step's one copy to the host
        sent = time.perf_counter()
        timings["act"] += sent - began
        self._on_device[t][self._groups.index(group)] = (obs, mask, result)
        a = a_logp_v[0].astype(np.int32)
        b.actions[t, rows], b.logp[t, rows], b.values[t, rows] = a, a_logp_v[1], a_logp_v[2]
        self.record_info(t, rows, group.info)
        checkpoint.tell_actions(group.view, a)
        group.step = t
        if len(self._groups) == 1:
            sent = time.perf_counter()
            group.sent = group.envs.step(a)
            timings["env"] += time.perf_counter() - sent
        else:
            group.envs.step_async(a)
            group.sent = True

    def record_info(self, t: int, rows: slice, info: dict[str, Any]) -> None:
        """A hook for subclasses that keep more of a step than PPO does: ``info`` is the info of
        the state environments ``rows`` acted in at step ``t`` (e.g. ``info["expert_action"]``,
        with ``expert=`` on the vector envs); a buffer added to the :class:`Rollout` and to its
        :meth:`~Rollout.batch` reaches the update's minibatches."""

    def _receive(self, group: _Group, t: int) -> None:
        """Records the outcome of ``group``'s step ``t``."""
        b, rows = self._buffers, group.rows
        if group.sent is True:
            began = time.perf_counter()
            obs, reward, terminated, truncated, info = group.envs.step_wait()
            self.timings["env"] += time.perf_counter() - began
        else:
            obs, reward, terminated, truncated, info = group.sent
        group.sent = None
        done = terminated | truncated
        b.rewards[t, rows], b.terminated[t, rows], b.done[t, rows] = reward, terminated, done
        score, length = self._score[rows], self._length[rows]
        score += reward
        length += 1
        if done.any():
            for i in np.flatnonzero(done):
                if not terminated[i]:  # truncated: bootstrapped from its last observation
                    self._truncations.append((t, rows.start + i, info["final_obs"][i]))
                self.recent_scores.append(float(score[i]))
                self.recent_lengths.append(int(length[i]))
                score[i], length[i] = 0.0, 0
            self.episodes += int(done.sum())
            del self.recent_scores[:-100], self.recent_lengths[:-100]
        group.obs = self.with_info(group.see(obs), info)
        group.mask, group.info = info["action_mask"], info

    def view(self) -> Callable[[np.ndarray], np.ndarray] | None:
        """A fresh, stateful ``obs (B, 40) -> model input (B, width)`` for one vector env of
        the trainer's, or ``None``: the model sees the observations themselves (PPO's). The
        critic of such a model reads only the first 40 columns (a truncated episode's last
        observation reaches it with the rest zero)."""
        return None

    def with_info(self, seen: np.ndarray, info: dict[str, Any]) -> np.ndarray:
        """The model's input of a step: ``seen`` (the observations through :meth:`view`), with
        what the model reads of the step's ``info`` after it (PPO's: nothing)."""
        return seen

    def _bootstrap(self) -> None:
        """The next values: the next step's values, 0 after a termination, and the critic's
        values of what follows the last step and of the truncated episodes' last observations
        (one call, its rows padded to a multiple of ``num_envs`` so that it compiles once)."""
        began = time.perf_counter()
        b, n = self._buffers, self.config.num_envs
        b.next_values[:-1] = b.values[1:]
        current = np.concatenate([group.obs for group in self._groups])
        finals = [final for _, _, final in self._truncations]
        padded = np.zeros((-(-(n + len(finals)) // n) * n, b.obs.shape[-1]), np.float32)
        padded[:n] = current
        if finals:  # the observations alone (the critic reads only those columns)
            padded[n : n + len(finals), :OBSERVATION_SIZE] = finals
        values = jax.device_get(_values(self.model, padded))
        b.next_values[-1] = values[:n]
        for k, (t, i, _) in enumerate(self._truncations):
            b.next_values[t, i] = values[n + k]
        b.next_values[b.terminated > 0] = 0.0
        self.timings["bootstrap"] += time.perf_counter() - began

    def update_coefs(self) -> Any:
        """What this iteration's update passes to its loss combiner (none for PPO itself)."""
        return None

    def rewards_of(self, rollout: Rollout) -> np.ndarray:
        """The rewards PPO learns from: the game's, scaled."""
        return rollout.rewards * self.config.reward_scale

    def step(self) -> dict[str, float]:
        """One iteration: collect, then update; returns the update's statistics."""
        rollout = self.collect()
        began = time.perf_counter()
        # What only the host has (rewards, episode ends, next values; the coefficients of a
        # variant's loss) crosses in one copy; the rest of the batch is on the device already.
        batch = rollout.batch(self.rewards_of(rollout))
        batch, coefs = jax.device_put((batch, self.update_coefs()))
        self.model, self.opt_state, stats = self._update(
            self.model, self.opt_state, batch, self._next_key(), coefs
        )
        stats = {k: float(v) for k, v in jax.device_get(stats).items()}
        self.timings["update"] += time.perf_counter() - began
        self.steps += self.per_iteration
        self.iteration += 1
        return stats

    def state(self) -> dict[str, Any]:
        """What a checkpoint needs beside the model to continue exactly where this left off."""
        return {
            "opt_state": self.opt_state,
            "key": self.key,
            "counts": np.array([self.steps, self.iteration, self.episodes], np.int64),
            # Fixed length (NaN-padded), so that a checkpoint always has the same shape.
            "recent_scores": np.array(
                self.recent_scores + [np.nan] * (100 - len(self.recent_scores))
            ),
        }

    def restore(self, model: ActorCritic, state: dict[str, Any], description: dict) -> None:
        """Continues from a checkpoint's model and :meth:`state`."""
        self.model, self.opt_state, self.key = model, state["opt_state"], state["key"]
        self.steps, self.iteration, self.episodes = (int(c) for c in state["counts"])
        scores = np.asarray(state["recent_scores"])
        self.recent_scores = [float(s) for s in scores if not np.isnan(s)]
        self.seed_ranges = list(description.get("data", {}).get("seed_ranges") or [])

    def seeds_trained_on(self) -> list[int]:
        """Every seed of :attr:`seed_ranges`."""
        return [s for first, last in self.seed_ranges for s in range(first, last + 1)]

    @property
    def mean_recent_score(self) -> float:
        return float(np.mean(self.recent_scores)) if self.recent_scores else float("nan")

    @property
    def mean_recent_length(self) -> float:
        """The mean length of the last 100 episodes this process saw end (NaN before one)."""
        return float(np.mean(self.recent_lengths)) if self.recent_lengths else float("nan")


#: What :func:`~dinerdash_agents.checkpoint.load` needs of a ``ppo`` or ``ppo-masked``
#: checkpoint (the same model; the name says which was trained).
CHECKPOINT = checkpoint.Hooks(config_from_json=config_from_json, init=init)

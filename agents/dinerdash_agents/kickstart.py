"""Kick-started PPO (``train ppo-kickstart``): masked PPO whose actor starts as a behaviour-cloning
network and is pulled, by a decaying auxiliary loss, toward a teacher's action at the states the
learner itself visits (Schmitt et al. 2018, "Kickstarting deep reinforcement learning"; the
demonstration term of DAPG, Rajeswaran et al. 2018, with the teacher asked on-line).

- **The actor** is the BC checkpoint's network itself (``--init DIR``, a ``bc`` checkpoint: one
  hidden ReLU layer, its observation scaling by ruleset v0's upper bounds, as BC trained it), so
  the run starts at BC's score instead of a random policy's; or a feed-forward ``dagger``
  checkpoint's network, with its :class:`~dinerdash_agents.dagger.MemoryFeatures` if it has
  them (the trainer then computes them for every environment, and the checkpoint's policy
  does when it plays). The critic is PPO's (two tanh layers over the observation scaled by the
  server's Spec; with ``critic_memory``, the actor's memory features too; with ``critic_lives``,
  the groups lost so far, which the actor does not see) and starts untrained. With
  ``actor_lives`` the actor's memory features also count the groups lost, from its observations
  (``MemoryFeatures(lives=True)``); the DAgger network's first layer gets those inputs with
  weights 0, so the run starts from the same policy.
- **Critic warm-up**: the first ``critic_warmup`` iterations update only the critic; the policy
  terms are multiplied by 0, so the actor's gradients, and with Adam its updates, are exactly 0.
  The policy then moves on advantages of a critic that already knows the BC policy's returns.
- **The teacher**: the vector env runs with ``expert=True`` (``--teacher expert``: the reference
  heuristic) or ``expert="planner"`` (``--teacher planner``: the look-ahead planner, which costs
  server CPU at every step), and ``info["expert_action"]`` is stored with each step.
- **The kick-starting loss**: ``λ_k · CE(π(·|s) over the legal actions, teacher's action)`` added
  to PPO's loss; ``λ_k`` falls from ``kick_coef`` to 0 linearly over the first ``kick_until`` of
  the iterations after the warm-up (``kick_schedule="linear"``), or geometrically by
  ``kick_decay`` per iteration (``"geometric"``). The schedule is in the checkpoint's config.

Everything else (sampling, GAE, the clipped update, checkpoints and ``--resume``) is
:class:`~dinerdash_agents.ppo.Trainer`'s.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from dinerdash.game import OBSERVATION_SIZE

from . import bc, checkpoint, dagger
from .errors import AgentsError
from .ppo import PPOConfig, Rollout, Trainer, _forward, _mlp, make_update, observation_scale

__all__ = [
    "LOST_COLUMNS",
    "TEACHERS",
    "KickstartConfig",
    "KickstartModel",
    "KickstartTrainer",
    "config_for_init",
    "init",
    "kick_coefficient",
    "kick_loss",
]

#: ``--teacher`` -> the vector env's ``expert`` keyword.
TEACHERS: dict[str, bool | str] = {"expert": True, "planner": "planner"}
#: ``critic_lives``: ``info["lost"]`` one-hot (:func:`~dinerdash_agents.dagger.lives_one_hot`),
#: after the actor's inputs.
LOST_COLUMNS = dagger.LIVES_SIZE


@dataclass(frozen=True)
class KickstartConfig(PPOConfig):
    """PPO's hyper-parameters (a smaller entropy bonus, as the actor starts sharp) plus the
    initialisation, the teacher and the schedules."""

    ent_coef: float = 0.003
    #: The checkpoint directory the actor started from, and its network's sizes: a ``bc`` one's,
    #: or with ``init_algorithm="dagger"`` the DAgger learner's whole config.
    init: str = ""
    bc_hidden: int = 512
    bc_dropout: float = 0.2
    init_algorithm: str = "bc"
    dagger_config: dict | None = None
    #: ``expert`` (the reference heuristic) or ``planner`` (the look-ahead planner).
    teacher: str = "expert"
    #: λ_k at the first iteration after the warm-up.
    kick_coef: float = 1.0
    #: ``linear``: λ_k reaches 0 after ``kick_until`` of the iterations that follow the warm-up;
    #: ``geometric``: λ_k is multiplied by ``kick_decay`` every iteration.
    kick_schedule: str = "linear"
    kick_until: float = 0.25
    kick_decay: float = 0.98
    #: Iterations at the start that update only the critic.
    critic_warmup: int = 10
    #: Whether the critic reads the actor's memory features too (a truncated episode's last
    #: observation reaches it with them zero); ``hidden`` is its width either way.
    critic_memory: bool = False
    #: Whether the critic also reads the groups lost so far (:data:`LOST_COLUMNS`; the episode
    #: ends at the fifth): an input of the critic's alone, the actor and so the policy that plays
    #: do not see it; a truncated episode's last observation reaches the critic with it zero.
    critic_lives: bool = False
    #: Whether the actor's memory features also count the groups lost, from the observations
    #: (a DAgger actor with memory; its new inputs start with weights 0).
    actor_lives: bool = False
    #: Whether the actor's memory features also hold each group's exact patience and grace
    #: buffer (``MemoryFeatures(patience=True)``; a DAgger actor with memory; its new inputs
    #: start with weights 0).
    actor_patience: bool = False

    def __post_init__(self) -> None:
        super().__post_init__()
        if not self.masked:
            raise TypeError("ppo-kickstart's policy is masked (masked=True)")
        if self.teacher not in TEACHERS:
            raise TypeError(f"teacher {self.teacher!r} is not one of {', '.join(TEACHERS)}")
        if self.kick_schedule not in ("linear", "geometric"):
            raise TypeError(f"kick_schedule {self.kick_schedule!r} is not linear or geometric")
        if self.init_algorithm not in INITS:
            raise TypeError(f"init_algorithm {self.init_algorithm!r} is not one of {INITS}")
        if (self.init_algorithm == "dagger") != (self.dagger_config is not None):
            raise TypeError("dagger_config goes with init_algorithm='dagger' (and only with it)")

    @property
    def memory(self) -> bool:
        """Whether the actor sees the DAgger learner's memory features."""
        return bool(self.dagger_config and self.dagger_config.get("memory"))

    @property
    def timers(self) -> bool:
        """Whether those features hold the timers too."""
        return bool(self.dagger_config and self.dagger_config.get("timers"))

    @property
    def lives(self) -> bool:
        """Whether they end with the groups lost, as the observations show them."""
        return bool(self.dagger_config and self.dagger_config.get("lives"))

    @property
    def patience(self) -> bool:
        """Whether they end with the groups' exact patience and grace buffers."""
        return bool(self.dagger_config and self.dagger_config.get("patience"))


def config_from_json(values: dict) -> KickstartConfig:
    return KickstartConfig(**values)


class KickstartModel(eqx.Module):
    """The BC (or DAgger) network as the actor, PPO's critic beside it. Calling it gives the
    actor's logits (dropout off), as every agent of this package does; the input is the
    observation (B, 40), with the memory features after it when the actor has them."""

    actor: bc.BehaviourCloning | dagger.DaggerNet
    critic: list[eqx.nn.Linear]
    #: The critic's observation scale (:func:`~dinerdash_agents.ppo.observation_scale`).
    scale: tuple[float, ...] = eqx.field(static=True)
    #: The input's columns the actor reads (the observation and its memory features); the
    #: critic's, as ``(start, stop)`` runs after the observation's 40.
    actor_width: int = eqx.field(static=True)
    critic_columns: tuple[tuple[int, int], ...] = eqx.field(static=True)

    def __init__(self, config: KickstartConfig, key: jax.Array) -> None:
        ka, kc = jax.random.split(key)
        if config.dagger_config is not None:
            self.actor = dagger.DaggerNet(dagger.config_from_json(config.dagger_config), ka)
        else:
            bc_config = bc.BCConfig(hidden=config.bc_hidden, dropout=config.bc_dropout)
            self.actor = bc.BehaviourCloning(bc_config, ka)
        self.actor_width = OBSERVATION_SIZE + dagger.memory_size(
            config.memory, config.timers, config.lives, config.patience
        )
        columns = []
        if config.critic_memory:
            columns.append((OBSERVATION_SIZE, self.actor_width))
        if config.critic_lives:
            columns.append((self.actor_width, self.actor_width + LOST_COLUMNS))
        self.critic_columns = tuple(columns)
        width = OBSERVATION_SIZE + sum(stop - start for start, stop in columns)
        self.critic = _mlp([width, config.hidden, config.hidden, 1], 1.0, kc)
        self.scale = observation_scale(config)

    @property
    def input_width(self) -> int:
        """The width of the rows it is given: the actor's columns, then the critic's own."""
        return max([self.actor_width, *(stop for _, stop in self.critic_columns)])

    def __call__(
        self, obs: jax.Array, mask: jax.Array | None = None, key: jax.Array | None = None
    ) -> jax.Array:
        del key  # never dropout: PPO's ratios need the policy that acted
        return self.actor(obs[:, : self.actor_width], mask)

    def value(self, obs: jax.Array) -> jax.Array:
        scaled = obs[:, :OBSERVATION_SIZE] / jnp.asarray(self.scale, jnp.float32)
        parts = [scaled, *(obs[:, start:stop] for start, stop in self.critic_columns)]
        return _forward(self.critic, jnp.concatenate(parts, axis=1))[:, 0]


def init(config: KickstartConfig, seed: int = 0) -> KickstartModel:
    """A model of ``config``'s shape with a random actor (a checkpoint's skeleton)."""
    return KickstartModel(config, jax.random.PRNGKey(seed))


#: The checkpoints an actor can start from: networks of one observation (and, for DAgger's,
#: its memory features) to the 57 logits.
INITS = ("bc", "dagger")


def _init_description(directory: str | Path) -> dict:
    """The description of the checkpoint ``directory``, which must be a ``bc`` or a ``dagger``
    one."""
    description = checkpoint.read_description(directory)
    found = description.get("algorithm")
    if found not in INITS:
        raise AgentsError(
            f"--init {directory}: a {found!r} checkpoint; ppo-kickstart starts from a 'bc' or a "
            "'dagger' one (its actor is that network)"
        )
    return description


def _load_init(directory: str | Path) -> tuple[bc.BehaviourCloning | dagger.DaggerNet, dict]:
    """The checkpoint ``directory``'s network and its description."""
    description = _init_description(directory)
    return checkpoint.load(directory, description["algorithm"]).model, description


def config_for_init(config: KickstartConfig, directory: str | Path) -> KickstartConfig:
    """``config`` with the checkpoint ``directory`` as its initialisation (path and sizes)."""
    description = _init_description(directory)
    sizes = description["config"]
    if description["algorithm"] == "dagger":
        # The memory features the actor gains (--actor-lives, --actor-patience).
        extra = {name: True for name in ("lives", "patience") if getattr(config, f"actor_{name}")}
        if extra and not sizes.get("memory"):
            flag = f"--actor-{next(iter(extra))}"
            raise AgentsError(
                f"{flag}: a memory feature, and --init {directory} has no memory (a dagger "
                "checkpoint trained with --memory)"
            )
        return replace(
            config,
            init=str(directory),
            init_algorithm="dagger",
            dagger_config=dagger.config_from_json({**sizes, **extra}).to_json(),
        )
    if config.actor_lives or config.actor_patience:
        raise AgentsError(
            f"--actor-lives and --actor-patience need a dagger --init with memory, not {directory}"
        )
    return replace(
        config,
        init=str(directory),
        bc_hidden=int(sizes["hidden"]),
        bc_dropout=float(sizes["dropout"]),
    )


def kick_coefficient(config: KickstartConfig, iteration: int, iterations: int) -> float:
    """λ_k of ``iteration`` (0-based) of a run of ``iterations``: ``kick_coef`` during the
    warm-up and at its end, then falling as ``kick_schedule`` says."""
    after = max(iteration - config.critic_warmup, 0)
    if config.kick_schedule == "geometric":
        return config.kick_coef * config.kick_decay**after
    span = max(config.kick_until * max(iterations - config.critic_warmup, 1), 1.0)
    return config.kick_coef * max(0.0, 1.0 - after / span)


def kick_loss(logits: jax.Array, mask: jax.Array, teacher: jax.Array) -> jax.Array:
    """Mean cross-entropy of the teacher's actions under the masked policy (``logits`` already
    masked); a step whose teacher action is illegal (none should be) counts 0."""
    logp = jax.nn.log_softmax(logits)
    picked = jnp.take_along_axis(logp, teacher[:, None], axis=1)[:, 0]
    legal = jnp.take_along_axis(mask, teacher[:, None], axis=1)[:, 0]
    return -jnp.where(legal, picked, 0.0).sum() / jnp.maximum(legal.sum(), 1)


class KickstartTrainer(Trainer):
    """Masked PPO from a BC actor, with critic warm-up and the decaying kick-starting loss.

    ``load_init=False`` (a resumed run) keeps a random actor of the right shape: the checkpoint's
    parameters replace it.
    """

    def __init__(
        self, config: KickstartConfig, total_steps: int, seed: int = 0, load_init: bool = True
    ) -> None:
        if not isinstance(config, KickstartConfig):
            raise TypeError("KickstartTrainer needs a KickstartConfig")
        if config.critic_memory and not config.memory:
            raise AgentsError(
                "--critic-memory: the critic reads the actor's memory features, and this actor "
                "has none (--init a dagger checkpoint trained with --memory)"
            )
        super().__init__(config, total_steps, seed)
        model = init(config, seed)
        if load_init:
            if not config.init:
                raise AgentsError("ppo-kickstart needs --init DIR (a bc or dagger checkpoint)")
            actor, description = _load_init(config.init)
            if config.actor_lives or config.actor_patience:
                learnt = dagger.config_from_json(description["config"])
                wanted = dagger.config_from_json(config.dagger_config)
                actor = _widened(actor, model, learnt, wanted)
            model = eqx.tree_at(lambda m: m.actor, model, actor)
        self.model = model
        self.opt_state = self.optimizer.init(eqx.filter(self.model, eqx.is_array))
        self._update = make_update(config, self.optimizer, combine=self._combine)
        self._buffers = Rollout(
            config.num_steps, config.num_envs, expert=True, width=self.model.input_width
        )

    def view(self):
        return _view(self.config)

    def with_info(self, seen: np.ndarray, info: dict[str, Any]) -> np.ndarray:
        """With ``critic_lives``, the groups lost (one-hot) after the actor's inputs."""
        if not self.config.critic_lives:
            return seen
        lost = dagger.lives_one_hot(np.asarray(info["lost"], np.int64))
        return np.concatenate([seen, lost], axis=1)

    def _combine(self, terms: dict, mb: dict, logits: jax.Array, coefs: dict):
        c = self.config
        kick = kick_loss(logits, mb["mask"], mb["expert_actions"])
        policy = terms["policy_loss"] - c.ent_coef * terms["entropy"] + coefs["kick"] * kick
        loss = coefs["policy_on"] * policy + c.vf_coef * terms["value_loss"]
        return loss, {"kick_loss": kick}

    def update_coefs(self) -> dict[str, jax.Array]:
        return coefficients(self.config, self.iteration, self.iterations)

    def record_info(self, t: int, rows: slice, info: dict[str, Any]) -> None:
        """Keeps the teacher's action of the state acted in."""
        expert = info.get("expert_action")
        if expert is None:
            raise AgentsError(
                "ppo-kickstart needs the teacher's actions: make the vector env with "
                f"expert={TEACHERS[self.config.teacher]!r}"
            )
        self._buffers.expert_actions[t, rows] = expert


def _widened(
    actor: dagger.DaggerNet,
    model: KickstartModel,
    learnt: dagger.DaggerConfig,
    wanted: dagger.DaggerConfig,
) -> dagger.DaggerNet:
    """``actor`` (whose inputs are ``learnt``'s) in ``model``'s actor (whose inputs are
    ``wanted``'s): its first layer's weights of each input block it learnt kept, those of the
    blocks it learnt without (``actor_lives``, ``actor_patience``) 0, so it plays as it did."""
    first = actor.layers[0].weight
    starts, at = {}, 0
    for name, width in dagger.input_blocks(learnt):
        starts[name], at = at, at + width
    columns = [
        first[:, starts[name] : starts[name] + width]
        if name in starts
        else jnp.zeros((first.shape[0], width), first.dtype)
        for name, width in dagger.input_blocks(wanted)
    ]
    actor = eqx.tree_at(lambda a: a.layers[0].weight, actor, jnp.concatenate(columns, 1))
    params, static = eqx.partition(model.actor, eqx.is_array)
    leaves = jax.tree_util.tree_leaves(eqx.filter(actor, eqx.is_array))
    return eqx.combine(
        jax.tree_util.tree_unflatten(jax.tree_util.tree_structure(params), leaves), static
    )


def coefficients(config: KickstartConfig, iteration: int, iterations: int) -> dict[str, Any]:
    """The update's ``coefs``: λ_k, and whether the policy terms count (0 in the warm-up)."""
    return {
        "kick": np.array(kick_coefficient(config, iteration, iterations), np.float32),
        "policy_on": np.array(iteration >= config.critic_warmup, np.float32),
    }


def _view(config: KickstartConfig):
    """An actor with memory sees its observations with a fresh
    :class:`~dinerdash_agents.dagger.MemoryFeatures` beside them (as it did when it learnt)."""
    return dagger.memory_view(config.memory, config.timers, config.lives, config.patience)


#: What :func:`~dinerdash_agents.checkpoint.load` needs of a ``ppo-kickstart`` checkpoint.
CHECKPOINT = checkpoint.Hooks(config_from_json=config_from_json, init=init, view=_view)

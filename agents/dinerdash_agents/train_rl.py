"""One reinforcement-learning run (``train ppo|ppo-masked|gail|ppo-kickstart``): the environments
on the server (one vector env, or with ``--pipeline K`` K vector envs whose steps the trainer
pipelines), a :class:`~dinerdash_agents.ppo.Trainer`, a progress bar, a learning curve, and
periodic atomic checkpoints that ``--resume`` continues from.

A checkpoint directory of an RL run holds what every checkpoint holds (``model.eqx``,
``checkpoint.json``) plus the trainer's state (``trainer.eqx``: optimiser state and random key)
and the learning curve (``curve.csv``, ``curve.png``). Losing the server stops the run with a
clear error after writing such a checkpoint, so no finished iteration is lost.

Beside the checkpoint, the live curves (:class:`~dinerdash_agents.curves.LiveCurves`): after every
iteration, at its environment steps, ``rollout/score`` and ``rollout/episode_length`` (means of
the last 100 training episodes), ``time/env_steps_per_s`` and the update's statistics as
``train/<name>`` (``policy_loss``, ``value_loss``, ``entropy``, ``approx_kl``, and a variant's
own, e.g. kick-starting's).
"""

from __future__ import annotations

import dataclasses
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import equinox as eqx
import gymnasium
from dinerdash.evaluation import Progress
from gymnasium.vector import AutoresetMode

from . import checkpoint, gail, kickstart, ppo
from ._version import __version__
from .connect import ConnectOptions, options, served
from .curves import LiveCurves, read_curve, write_curve
from .demos import load_demos
from .errors import AgentsError
from .seeds import as_ranges, trained_on

__all__ = ["PIPELINE", "RL", "RL_ALGORITHMS", "RLAlgorithm", "make_envs", "train_rl"]


@dataclass(frozen=True)
class RLAlgorithm:
    """What a run of one RL algorithm needs beyond masked PPO's."""

    #: Whether its policy is restricted to the legal actions.
    masked: bool
    #: ``trainer(config, total_steps, seed, demos, resumed)``; a resumed run's model comes from
    #: its checkpoint.
    trainer: Callable[..., ppo.Trainer]
    #: Its default config, given ``masked``.
    config: Callable[..., ppo.PPOConfig] = ppo.PPOConfig
    #: It learns from demonstrations (``--demos``).
    needs_demos: bool = False
    #: ``start(config, init, teacher, resumed)``: the config of a run that starts from a
    #: checkpoint (``--init``) with a teacher (``--teacher``); ``None``: it takes neither.
    start: Callable[..., ppo.PPOConfig] | None = None
    #: ``game(config)``: the game keywords its environments need (e.g. ``expert=``).
    game: Callable[[ppo.PPOConfig], dict[str, Any]] = lambda config: {}


def _ppo(config, steps, seed, demos, resumed) -> ppo.Trainer:
    return ppo.Trainer(config, steps, seed=seed)


def _gail(config, steps, seed, demos, resumed) -> ppo.Trainer:
    return gail.GAILTrainer(config, steps, seed=seed, demos=demos)


def _kickstart(config, steps, seed, demos, resumed) -> ppo.Trainer:
    # A resumed run's actor comes from its checkpoint, not from --init.
    return kickstart.KickstartTrainer(config, steps, seed=seed, load_init=not resumed)


def _kickstart_config(
    config: ppo.PPOConfig, init: str | Path | None, teacher: str | None, resumed: bool
) -> ppo.PPOConfig:
    """A new ppo-kickstart run's config: its initialisation and teacher; a resumed run's as it
    was (``--teacher`` must agree with it)."""
    if resumed:
        if teacher is not None and teacher != config.teacher:
            raise AgentsError(
                f"--teacher {teacher}: the run being resumed has teacher {config.teacher!r}"
            )
        return config
    if not isinstance(config, kickstart.KickstartConfig):
        config = kickstart.KickstartConfig(**config.to_json())
    config = dataclasses.replace(config, teacher=teacher or config.teacher)
    return kickstart.config_for_init(config, init)


#: The RL algorithms of ``train``.
RL: dict[str, RLAlgorithm] = {
    "ppo": RLAlgorithm(masked=False, trainer=_ppo),
    "ppo-masked": RLAlgorithm(masked=True, trainer=_ppo),
    "gail": RLAlgorithm(masked=True, trainer=_gail, needs_demos=True),
    "ppo-kickstart": RLAlgorithm(
        masked=True,
        trainer=_kickstart,
        config=kickstart.KickstartConfig,
        start=_kickstart_config,
        game=lambda config: {"expert": kickstart.TEACHERS[config.teacher]},
    ),
}
#: RL algorithm name -> whether its policy is masked.
RL_ALGORITHMS = {name: entry.masked for name, entry in RL.items()}
TRAINER_STATE = "trainer.eqx"
CURVE_COLUMNS = ("env_steps", "mean_score_last_100_episodes", "env_steps_per_s")
#: Seconds between two periodic checkpoints.
CHECKPOINT_EVERY = 120.0
#: Vector envs the environments are split into by default. With 2 the server steps one while the
#: trainer acts for the other (:meth:`~dinerdash_agents.ppo.Trainer.attach`), but on 2 shared
#: cores that cost more (a second call and thread hand-offs per step) than it hid: the server
#: spends ~3 % of a core (docs/agents.md, "Speed"). The samples do not depend on it.
PIPELINE = 1


def make_envs(
    config: ppo.PPOConfig,
    connect: ConnectOptions | str | list[str] | None,
    pipeline: int = PIPELINE,
    **game: Any,
) -> list[Any]:
    """The ``config.num_envs`` training environments as ``pipeline`` SAME_STEP vector envs of as
    equal sizes as can be (fewer if there are fewer environments), in order, connected as
    ``connect`` says (an address alone will do); ``game``: the game keywords (``expert=``)."""
    import dinerdash  # noqa: F401  (registers DinerDash-v0)

    if not isinstance(connect, ConnectOptions):
        connect = ConnectOptions(address=connect)

    n = config.num_envs
    k = max(1, min(pipeline, n))
    envs: list[Any] = []
    try:
        for j in range(k):
            envs.append(
                gymnasium.make_vec(
                    "dinerdash:DinerDash-v0",
                    num_envs=n // k + (j < n % k),
                    connect=connect,
                    autoreset_mode=AutoresetMode.SAME_STEP,
                    max_episode_steps=config.max_episode_steps,
                    **game,
                )
            )
    except BaseException:
        for e in envs:
            e.close()
        raise
    return envs


class _Spent:
    """Training time: what a resumed run had spent before, plus this process's since it began."""

    def __init__(self, wall: float = 0.0, cpu: float = 0.0) -> None:
        self._wall, self._cpu = wall - time.monotonic(), cpu - time.process_time()

    def wall(self) -> float:
        return self._wall + time.monotonic()

    def cpu(self) -> float:
        return self._cpu + time.process_time()


def _description(trainer: ppo.Trainer, algorithm: str, name: str, spent: _Spent) -> dict:
    return {
        "name": name,
        "algorithm": algorithm,
        "package_version": __version__,
        "config": trainer.config.to_json(),
        "data": {
            "environment_steps": trainer.steps,
            "episodes": trainer.episodes,
            "seed_ranges": trainer.seed_ranges,
        },
        "training": {
            "seed": trainer.seed,
            "total_steps": trainer.total_steps,
            "iterations": trainer.iteration,
            "seconds": round(spent.wall(), 3),
            "cpu_seconds": round(spent.cpu(), 3),
            "mean_recent_score": trainer.mean_recent_score,
        },
    }


def _save(trainer: ppo.Trainer, out: Path, algorithm: str, spent: _Spent) -> None:
    description = _description(trainer, algorithm, out.name, spent)

    def extra(tmp: Path) -> None:
        eqx.tree_serialise_leaves(tmp / TRAINER_STATE, trainer.state())
        title = algorithm if out.name == algorithm else f"{algorithm}: {out.name}"
        write_curve(
            tmp,
            CURVE_COLUMNS,
            trainer.curve,
            lines={"mean_score_last_100_episodes": "mean score"},
            xlabel="environment steps",
            ylabel="mean score, last 100 training episodes",
            title=title,
        )

    checkpoint.save(out, trainer.model, description, extra=extra)


def _resume(directory: Path, algorithm: str, steps: int | None, demos: Any) -> tuple[Any, _Spent]:
    description = checkpoint.read_description(directory)
    found = description.get("algorithm")
    if found != algorithm:
        raise AgentsError(
            f"{directory / checkpoint.DESCRIPTION}: field 'algorithm' is {found!r}; "
            f"cannot resume it as {algorithm}"
        )
    config = checkpoint.lookup(algorithm).config_from_json(description["config"])
    training = description["training"]
    total = steps if steps is not None else training["total_steps"]
    trainer = RL[algorithm].trainer(config, total, training["seed"], demos, True)
    policy = checkpoint.load(directory, algorithm)
    try:
        state = eqx.tree_deserialise_leaves(directory / TRAINER_STATE, trainer.state())
    except Exception as e:  # a missing or foreign file
        raise AgentsError(f"{directory / TRAINER_STATE} cannot be resumed from: {e!r}") from e
    trainer.restore(policy.model, state, description)
    steps_, score, rate = CURVE_COLUMNS
    trainer.curve = [
        (int(row[steps_]), float(row[score]), float(row[rate])) for row in read_curve(directory)
    ]
    return trainer, _Spent(training["seconds"], training.get("cpu_seconds", 0.0))


def train_rl(
    algorithm: str,
    steps: int | None,
    out: str | Path,
    *,
    num_envs: int | None = None,
    address: str | list[str] | None = None,
    connect: ConnectOptions | None = None,
    demos: str | Path | None = None,
    seed: int = 0,
    resume: str | Path | None = None,
    config: ppo.PPOConfig | None = None,
    progress: bool = True,
    pipeline: int = PIPELINE,
    init: str | Path | None = None,
    teacher: str | None = None,
    tensorboard: str | Path | None = None,
    **connection: Any,
) -> ppo.Trainer:
    """Trains ``algorithm`` for ``steps`` environment steps in all (counting a resumed run's),
    checkpointing to ``out``; returns the trainer. ``pipeline``: vector envs the environments
    are split into (:func:`make_envs`; the samples do not depend on it, only the speed).
    ``init`` and ``teacher`` (``ppo-kickstart``): the BC (or DAgger) checkpoint its actor starts
    from and whose actions it is pulled toward (``expert`` or ``planner``). ``connect``: how to
    reach the server(s) (:class:`dinerdash.ConnectOptions`; ``address`` and the connection
    keywords ``timeout``, ``tls``, ``tls_ca``, ... are put in; none named:
    ``DINERDASH_ADDRESS``, else a local server started here). ``tensorboard``: the directory
    of the live curves (``None``: none written)."""
    if algorithm not in RL:
        raise AgentsError(f"unknown RL algorithm {algorithm!r} (known: {', '.join(RL)})")
    entry = RL[algorithm]
    connect = options(connect, "train_rl", address, **connection)
    if entry.needs_demos and demos is None:
        raise AgentsError(
            f"{algorithm} needs --demos (a file written by python -m dinerdash collect)"
        )
    if steps is not None and steps < 1:
        raise AgentsError(f"--steps must be at least 1 (got {steps})")
    if pipeline < 1:
        raise AgentsError(f"--pipeline must be at least 1 (got {pipeline})")
    if entry.start is not None and init is None and resume is None:
        raise AgentsError(
            f"{algorithm} needs --init DIR (a bc or dagger checkpoint) or --resume DIR"
        )
    if (init is not None or teacher is not None) and entry.start is None:
        starters = ", ".join(name for name, e in RL.items() if e.start is not None)
        raise AgentsError(f"--init and --teacher are {starters}'s; {algorithm} takes neither")
    out = Path(out)
    # A local server, if any, starts before any JAX work.
    with served(connect) as (connect, _):
        trainer, spent, config, demo_data = _prepare(
            algorithm, steps, num_envs, demos, resume, config
        )
        if entry.start is not None:
            config = entry.start(config, init, teacher, trainer is not None)
        envs = make_envs(config, connect, pipeline, **entry.game(config))
        try:
            if trainer is None:
                if config.observation_high is None:
                    # The networks scale the observation by the bounds of the server's Spec.
                    high = envs[0].single_observation_space.high
                    config = dataclasses.replace(config, observation_high=tuple(high.tolist()))
                trainer = entry.trainer(config, steps, seed, demo_data, False)
                trainer.seed_ranges = _seeds_learnt_from(demo_data, init)
            live = LiveCurves(tensorboard, resumed=resume is not None, step=trainer.steps)
            with live:
                _run(trainer, envs, out, algorithm, spent, progress, live)
        finally:
            for e in envs:
                e.close()
        _save(trainer, out, algorithm, spent)
        return trainer


def _seeds_learnt_from(demos: Any, init: str | Path | None) -> list[list[int]]:
    """The seeds a new run learns from beyond its environments': its demonstrations' (GAIL) and
    those its starting checkpoint (``--init``) was trained on."""
    seeds = [] if demos is None or demos.seeds is None else [int(s) for s in demos.seeds]
    if init is not None:
        ranges = trained_on(checkpoint.read_description(init))
        seeds += [s for r in ranges for s in r]
    return as_ranges(seeds)


def _prepare(
    algorithm: str,
    steps: int | None,
    num_envs: int | None,
    demos: str | Path | None,
    resume: str | Path | None,
    config: ppo.PPOConfig | None,
) -> tuple[ppo.Trainer | None, _Spent, ppo.PPOConfig, Any]:
    """The resumed trainer, or ``None`` for a new run (its trainer is made once the environments
    are there); the time spent, the run's config and the demonstrations (``None`` without)."""
    demo_data = load_demos(demos, None) if demos is not None else None
    if resume is not None:
        trainer, spent = _resume(Path(resume), algorithm, steps, demo_data)
        if num_envs is not None and num_envs != trainer.config.num_envs:
            raise AgentsError(
                f"--num-envs {num_envs}: the run in {resume} has {trainer.config.num_envs} "
                "environments, and a resumed run keeps them"
            )
        return trainer, spent, trainer.config, demo_data
    if steps is None:
        raise AgentsError("--steps is needed (or --resume DIR)")
    config = config or RL[algorithm].config(masked=RL[algorithm].masked)
    if num_envs is not None:  # the rollout and minibatches adapted (PPOConfig.for_num_envs)
        config = config.for_num_envs(num_envs)
    return None, _Spent(), config, demo_data


def _run(
    trainer: ppo.Trainer,
    envs: Any,
    out: Path,
    algorithm: str,
    spent: _Spent,
    progress: bool,
    live: LiveCurves,
) -> None:
    """Iterations on ``envs`` until the trainer has done them all, each added to the curve and
    the live curves, checkpointing every :data:`CHECKPOINT_EVERY` seconds; a lost server
    checkpoints and raises :class:`AgentsError`."""
    # The bar counts this process's environment steps (a resumed run's earlier ones aside), so
    # that its rate is env-steps/s.
    remaining = trainer.iterations * trainer.per_iteration - trainer.steps
    bar = Progress(remaining, algorithm) if progress else None
    last_save = time.monotonic()
    try:
        trainer.attach(envs)
        while trainer.iteration < trainer.iterations:
            began, steps_before = time.monotonic(), trainer.steps
            stats = trainer.step()
            rate = (trainer.steps - steps_before) / max(time.monotonic() - began, 1e-9)
            trainer.curve.append((trainer.steps, trainer.mean_recent_score, round(rate, 1)))
            live.add(
                trainer.steps,
                {
                    "rollout/score": trainer.mean_recent_score,
                    "rollout/episode_length": trainer.mean_recent_length,
                    "time/env_steps_per_s": rate,
                    **{f"train/{name}": value for name, value in stats.items()},
                },
            )
            if bar is not None:
                bar.desc = f"{algorithm} score {trainer.mean_recent_score:,.0f}"
                bar.update(trainer.per_iteration)
            if time.monotonic() - last_save >= CHECKPOINT_EVERY:
                _save(trainer, out, algorithm, spent)
                last_save = time.monotonic()
    except Exception as e:
        from dinerdash.errors import ServiceError

        if not isinstance(e, ServiceError) or trainer.iteration == 0:
            raise
        _save(trainer, out, algorithm, spent)
        raise AgentsError(
            f"lost the server after {trainer.steps} environment steps ({e}); the run is "
            f"checkpointed in {out}: continue it with --resume {out}"
        ) from e
    finally:
        if bar is not None:
            bar.close()

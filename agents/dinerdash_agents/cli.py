"""``python -m dinerdash_agents`` (also ``dinerdash-agents``): train, evaluate, and the paper's
experiment end to end.

::

    python -m dinerdash_agents train bc --demos demos/dinerdash_expert.npz --out runs/bc
    python -m dinerdash_agents evaluate runs/bc --episodes 100 --seed 1000 --json
    python -m dinerdash_agents paper --out docs/results
    python -m dinerdash_agents recipe --seed 0 --out runs/recipe-0
    python -m dinerdash_agents bench-ppo --num-envs 256 --iterations 10

Every command that talks to a server takes ``--address host:port`` (several separated by
commas); without it (and without ``DINERDASH_ADDRESS``) a local ``dinerdash-server`` is started
and stopped, as in ``python -m dinerdash``; and ``--tls``, ``--tls-ca PATH`` and ``--timeout``
as there (:mod:`dinerdash.cli`, which both programs share).

The commands are shells over :mod:`~dinerdash_agents.train_imitation`,
:mod:`~dinerdash_agents.train_rl`, :mod:`~dinerdash_agents.evaluate`,
:mod:`~dinerdash_agents.paper`, :mod:`~dinerdash_agents.recipe` and
:mod:`~dinerdash_agents.bench`.
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Sequence

from dinerdash import ConnectOptions
from dinerdash.cli import (
    DefaultsHelpFormatter,
    add_connection_arguments,
    connection_keywords,
    run_command,
    summary,
)

__all__ = ["main"]


def _connect(args: argparse.Namespace) -> ConnectOptions:
    """The one connection value of a command: ``--address``, ``--timeout``, ``--tls``, ..."""
    return ConnectOptions(address=args.address, **connection_keywords(args))


def _cmd_train(args: argparse.Namespace) -> int:
    from .curves import tensorboard_dir
    from .train_rl import RL_ALGORITHMS

    args.tensorboard = tensorboard_dir(args.out, args.tensorboard)

    runs = {
        "dagger": _cmd_train_dagger,
        "dagger-recurrent": _cmd_train_recurrent,
        **dict.fromkeys(RL_ALGORITHMS, _cmd_train_rl),
    }
    return runs.get(args.algorithm, _cmd_train_imitation)(args)


def _cmd_train_imitation(args: argparse.Namespace) -> int:
    from .errors import AgentsError
    from .train_imitation import default_config, train_checkpoint

    if args.demos is None:
        raise AgentsError(f"{args.algorithm} needs --demos")

    config = default_config(args.algorithm, epochs=args.epochs, loss=args.loss)
    _, description = train_checkpoint(
        args.algorithm,
        args.demos,
        args.out,
        episodes=args.episodes,
        seed=args.seed,
        config=config,
        tensorboard=args.tensorboard,
    )
    data, training = description["data"], description["training"]
    print(
        f"wrote {args.out}: {args.algorithm} ({config.loss} loss) on {data['episodes']} episodes "
        f"({data['steps']} steps) of {args.demos} in {training['seconds']:.1f} s "
        f"({training['cpu_seconds']:.1f} s of CPU)"
    )
    return 0


def _cmd_train_rl(args: argparse.Namespace) -> int:
    from .errors import AgentsError
    from .kickstart import KickstartConfig
    from .train_rl import train_rl

    config = None
    given = {"kick_coef": args.kick_coef, "hidden": args.hidden, "update_epochs": args.epochs}
    given.update(
        {k: getattr(args, k) for k in ("learning_rate", "gamma", "gae_lambda", "ent_coef")}
    )
    given = {k: v for k, v in given.items() if v is not None}
    switches = ("critic_memory", "critic_lives", "actor_lives", "actor_patience")
    given.update({k: True for k in switches if getattr(args, k)})
    if given:
        if args.algorithm != "ppo-kickstart" or args.resume is not None:
            raise AgentsError(
                "--kick-coef, --critic-memory, --critic-lives, --actor-lives, --actor-patience, "
                "--hidden, --epochs, --learning-rate, --gamma, --gae-lambda and --ent-coef are a "
                "new ppo-kickstart run's (a resumed run keeps its settings)"
            )
        try:
            config = KickstartConfig(**given)
        except ValueError as e:
            raise AgentsError(str(e)) from e
    trainer = train_rl(
        args.algorithm,
        args.steps,
        args.out,
        num_envs=args.num_envs,
        connect=_connect(args),
        demos=args.demos,
        seed=args.seed,
        resume=args.resume,
        pipeline=args.pipeline,
        init=args.init,
        teacher=args.teacher,
        config=config,
        tensorboard=args.tensorboard,
    )
    print(
        f"wrote {args.out}: {args.algorithm} after {trainer.steps} environment steps, "
        f"mean score of the last 100 episodes {trainer.mean_recent_score:.1f}"
    )
    return 0


def _cmd_train_dagger(args: argparse.Namespace) -> int:
    import dataclasses

    from .dagger import DaggerConfig
    from .train_dagger import train_dagger

    given = {
        "teacher": args.teacher,
        "rounds": args.rounds,
        "episodes_per_round": args.episodes_per_round,
        "schedule": args.beta_schedule,
        "p": args.beta_p,
        "num_envs": args.num_envs,
        "hidden": args.hidden,
        "layers": args.layers,
        "epochs": args.epochs,
        "seat_weight": args.seat_weight,
        "memory": True if args.memory else None,
        "timers": True if args.timers else None,
        "patience": True if args.patience else None,
        "learner_memory": args.learner_memory,
        "learner_noise": args.learner_noise,
    }
    config = dataclasses.replace(
        DaggerConfig(), **{k: v for k, v in given.items() if v is not None}
    )
    _, description = train_dagger(
        args.out, config, connect=_connect(args), seed=args.seed, tensorboard=args.tensorboard
    )
    data, training = description["data"], description["training"]
    print(
        f"wrote {args.out}: dagger (teacher {config.teacher}), {config.rounds} rounds of "
        f"{config.episodes_per_round} episodes ({data['steps']:,} labelled states), best round "
        f"{training['best_round']} ({training['best_validation_mean_score']:,.1f} on seeds "
        f"{training['validation_seeds']}) in {training['seconds']:.1f} s"
    )
    return 0


def _cmd_train_recurrent(args: argparse.Namespace) -> int:
    import dataclasses

    from .recurrent import RecurrentConfig
    from .train_dagger import train_dagger

    given = {
        "teacher": args.teacher,
        "kind": args.kind,
        "stack": args.stack,
        "rounds": args.rounds,
        "episodes_per_round": args.episodes_per_round,
        "p": args.beta_p,
        "num_envs": args.num_envs,
        "hidden": args.hidden,
        "chunk": args.chunk,
        "epochs": args.epochs,
        "seat_weight": args.seat_weight,
        "memory": True if args.memory else None,
    }
    config = dataclasses.replace(
        RecurrentConfig(), **{k: v for k, v in given.items() if v is not None}
    )
    _, description = train_dagger(
        args.out, config, connect=_connect(args), seed=args.seed, tensorboard=args.tensorboard
    )
    data, training = description["data"], description["training"]
    print(
        f"wrote {args.out}: dagger-recurrent ({config.kind}, teacher {config.teacher}), "
        f"{config.rounds} rounds of {config.episodes_per_round} episodes ({data['steps']:,} "
        f"labelled states), best round {training['best_round']} "
        f"({training['best_validation_mean_score']:,.1f} on seeds "
        f"{training['validation_seeds']}) in {training['seconds']:.1f} s"
    )
    return 0


def _cmd_evaluate(args: argparse.Namespace) -> int:
    import time

    from dinerdash.evaluation import Progress, print_evaluation

    from . import seeds
    from .checkpoint import load
    from .evaluate import evaluate_policy

    policy = load(args.checkpoint)
    if args.episodes < 1:
        print("error: --episodes must be at least 1", file=sys.stderr)
        return 2
    trained = seeds.trained_on(policy.description)
    seed = args.seed
    if seed is None:
        seed = seeds.evaluation_seed(trained, args.episodes)
        if seed != seeds.EVALUATION_SEEDS.start:
            print(
                f"note: {policy.name} was trained on seeds {seeds.spelled(trained)}: evaluating "
                f"on the unseen seeds {seed}..{seed + args.episodes - 1}",
                file=sys.stderr,
            )
    warning = seeds.overlap_warning(policy.name, trained, seed, args.episodes)
    if warning is not None:
        print(f"warning: {warning}", file=sys.stderr)
    progress = Progress(args.episodes, policy.name)
    start = time.monotonic()
    scores, lengths = evaluate_policy(
        policy.act,
        args.episodes,
        connect=_connect(args),
        seed=seed,
        num_envs=args.num_envs,
        max_steps=args.max_steps,
        use_mask=not args.no_mask,
        progress=progress,
    )
    progress.close()
    print_evaluation(
        policy.name + (" (no mask)" if args.no_mask else ""),
        scores,
        lengths,
        seed=seed,
        how=f"the client's vector env ({min(args.num_envs, args.episodes)} environments)",
        elapsed=time.monotonic() - start,
        as_json=args.json,
    )
    return 0


def _cmd_paper(args: argparse.Namespace) -> int:
    from .paper import run_paper

    run_paper(
        args.out,
        connect=_connect(args),
        demos=args.demos,
        seed=args.seed,
        rl_steps=args.rl_steps,
        update=args.update,
        tensorboard=args.tensorboard,
    )
    return 0


def _cmd_recipe(args: argparse.Namespace) -> int:
    from .recipe import run_recipe

    record = run_recipe(args.out, seed=args.seed, ppo_steps=args.ppo_steps, connect=_connect(args))
    stages = ", ".join(f"{name} {seconds:,.0f} s" for name, seconds in record["stages"].items())
    print(f"wrote {args.out}: training seed {args.seed}, {stages} ({record['seconds']:,.0f} s)")
    return 0


def _cmd_bench_ppo(args: argparse.Namespace) -> int:
    import json

    from .bench import bench_ppo, print_bench

    result = bench_ppo(
        algorithm=args.algorithm,
        num_envs=args.num_envs,
        iterations=args.iterations,
        pipeline=args.pipeline,
        init=args.init,
        connect=_connect(args),
    )
    print_bench(result)
    if args.json:
        print(json.dumps(result))
    return 0


def _parser() -> argparse.ArgumentParser:
    from .recipe import PPO_STEPS
    from .train_rl import PIPELINE

    parser = argparse.ArgumentParser(
        prog="python -m dinerdash_agents", description=summary(__doc__)
    )
    sub = parser.add_subparsers(dest="command", required=True)

    p = sub.add_parser(
        "train",
        help="train an agent: on expert demonstrations (bc, dpgm), on the server (RL) or with a "
        "teacher labelling the learner's states (dagger)",
        formatter_class=DefaultsHelpFormatter,
    )
    p.add_argument(
        "algorithm",
        choices=[
            "bc",
            "dpgm",
            "ppo",
            "ppo-masked",
            "gail",
            "ppo-kickstart",
            "dagger",
            "dagger-recurrent",
        ],
    )
    p.add_argument(
        "--demos",
        help="the .npz written by `python -m dinerdash collect` (bc, dpgm and gail need it)",
    )
    p.add_argument(
        "--episodes", type=int, default=None, help="train on the first K episodes (default: all)"
    )
    p.add_argument("--out", required=True, help="checkpoint directory to write")
    p.add_argument(
        "--tensorboard",
        metavar="DIR",
        help="directory of the run's TensorBoard event files, written as it goes (default: "
        "tensorboard/NAME beside the checkpoint OUT = .../NAME; view with `tensorboard --logdir "
        "DIR`)",
    )
    p.add_argument("--seed", type=int, default=0, help="initialisation and shuffling seed")
    p.add_argument(
        "--epochs",
        type=int,
        default=None,
        help="epochs (of every stage, for dpgm; default: tuned); ppo-kickstart: passes over "
        "each rollout (default 2)",
    )
    p.add_argument(
        "--loss",
        choices=["masked", "plain"],
        default="masked",
        help="masked: softmax over the legal actions of each step; plain: over all 57 "
        "(the paper's)",
    )
    p.add_argument("--steps", type=int, help="RL: environment steps in all (resumed ones included)")
    p.add_argument(
        "--num-envs",
        type=int,
        help="RL and dagger: environments stepped together (default 256; dagger 32)",
    )
    p.add_argument("--resume", help="RL: continue the run checkpointed in this directory")
    p.add_argument(
        "--pipeline",
        type=int,
        default=PIPELINE,
        help="RL: vector envs the environments are split into, one stepped by the server while "
        f"the trainer acts for another (default {PIPELINE}: one, no overlap); speed only",
    )
    p.add_argument(
        "--init",
        help="ppo-kickstart: the checkpoint its policy starts from (bc, or a feed-forward "
        "dagger one, whose memory features it keeps)",
    )
    p.add_argument(
        "--kick-coef",
        type=float,
        help="ppo-kickstart: the pull toward the teacher at the start (default 1; 0: none, "
        "PPO from the --init policy)",
    )
    p.add_argument(
        "--teacher",
        choices=["expert", "planner"],
        default=None,
        help="ppo-kickstart: whose action (info['expert_action']) the policy is pulled toward "
        "(default expert); dagger: who labels the learner's states",
    )
    p.add_argument("--rounds", type=int, help="dagger: rounds of play and retraining")
    p.add_argument("--episodes-per-round", type=int, help="dagger: training episodes per round")
    p.add_argument(
        "--beta-schedule",
        choices=["exponential", "first"],
        help="dagger: β_i = p^(i-1), or β_1 = 1 then 0",
    )
    p.add_argument("--beta-p", type=float, help="dagger: p of the exponential schedule")
    p.add_argument(
        "--hidden",
        type=int,
        help="dagger: units per hidden layer; ppo-kickstart: the critic's (default 128)",
    )
    p.add_argument(
        "--critic-memory",
        action="store_true",
        help="ppo-kickstart: the critic also reads the --init DAgger learner's memory features",
    )
    p.add_argument(
        "--critic-lives",
        action="store_true",
        help="ppo-kickstart: the critic also reads the groups lost so far (the actor does not)",
    )
    p.add_argument(
        "--actor-lives",
        action="store_true",
        help="ppo-kickstart: the actor's memory also counts the groups lost, from its observations",
    )
    p.add_argument(
        "--actor-patience",
        action="store_true",
        help="ppo-kickstart: the actor's memory also holds each group's exact patience",
    )
    p.add_argument(
        "--learning-rate",
        type=float,
        help="ppo-kickstart: Adam's step size at the start, falling linearly to 0 (default 3e-4)",
    )
    p.add_argument("--gamma", type=float, help="ppo-kickstart: the discount (default 0.995)")
    p.add_argument("--gae-lambda", type=float, help="ppo-kickstart: GAE's λ (default 0.95)")
    p.add_argument(
        "--ent-coef", type=float, help="ppo-kickstart: the entropy bonus's weight (default 0.003)"
    )
    p.add_argument("--layers", type=int, help="dagger: hidden layers")
    p.add_argument(
        "--seat-weight",
        type=float,
        help="dagger: loss weight of the states where the teacher seats a group (others: 1)",
    )
    p.add_argument(
        "--memory",
        action="store_true",
        help="dagger, dagger-recurrent: the learner also sees, per table and queue place, the "
        "steps since its group's patience level changed (computed from the episode's "
        "observations)",
    )
    p.add_argument(
        "--timers",
        action="store_true",
        help="dagger, with --memory: the memory also holds, per table, the steps since its "
        "status changed and since its order reached the kitchen, and the steps since the last "
        "group arrived",
    )
    p.add_argument(
        "--patience",
        action="store_true",
        help="dagger, with --memory: the memory also holds each group's exact patience and "
        "grace buffer (from the observations and the actions played)",
    )
    p.add_argument(
        "--learner-memory",
        choices=["played", "own"],
        help="dagger, with --patience: what the learner's own memory is told while it plays a "
        "round, the actions played (default) or its own choices (its patience beliefs then err "
        "where the teacher acted; docs/agents.md)",
    )
    p.add_argument(
        "--learner-noise",
        type=float,
        help="dagger: per step where the learner acts, the chance its action is replaced by a "
        "legal one drawn uniformly (DART's noise; default 0)",
    )
    p.add_argument(
        "--kind",
        choices=["gru", "stack"],
        help="dagger-recurrent: a GRU over the episode's observations, or an MLP over the last "
        "--stack observations",
    )
    p.add_argument("--stack", type=int, help="dagger-recurrent --kind stack: observations seen")
    p.add_argument("--chunk", type=int, help="dagger-recurrent: steps of a truncated-BPTT chunk")
    add_connection_arguments(p)
    p.set_defaults(func=_cmd_train)

    p = sub.add_parser(
        "evaluate",
        help="mean ± sd score of a checkpoint over seeded episodes",
        formatter_class=DefaultsHelpFormatter,
    )
    p.add_argument("checkpoint", help="checkpoint directory")
    p.add_argument("--episodes", type=int, default=100, help="episodes to play")
    p.add_argument(
        "--seed",
        type=int,
        default=None,
        help="seed of the first episode (episode i: seed + i); a warning names the seeds the "
        "checkpoint was trained on if they overlap (default: the evaluation seeds' first, 1000, "
        "or, if the checkpoint was trained on some of the seeds from there, the first seed after "
        "them)",
    )
    p.add_argument(
        "--max-steps", type=int, default=100_000, help="truncate an episode after this many steps"
    )
    p.add_argument("--num-envs", type=int, default=64, help="environments stepped together")
    p.add_argument("--json", action="store_true", help="also print the per-episode scores as JSON")
    p.add_argument(
        "--no-mask", action="store_true", help="greedy over all 57 actions, not the legal ones"
    )
    add_connection_arguments(p)
    p.set_defaults(func=_cmd_evaluate)

    p = sub.add_parser(
        "paper",
        help="the paper's experiment: collect, train every agent, evaluate, report",
        formatter_class=DefaultsHelpFormatter,
    )
    p.add_argument("--out", required=True, help="results directory (e.g. docs/results)")
    p.add_argument(
        "--demos",
        default=None,
        help="use this demonstrations file instead of collecting seeds 0..273 again",
    )
    p.add_argument("--seed", type=int, default=0, help="training seed of every agent")
    p.add_argument(
        "--rl-steps",
        type=int,
        default=None,
        help="environment steps of each RL agent (default: 3e7 for PPO, 1e7 for GAIL); a run "
        "already checkpointed under OUT/checkpoints is continued to it, or only loaded",
    )
    p.add_argument(
        "--update",
        action="store_true",
        help="keep the rows of OUT/results.json, train and evaluate only the agents it lacks, "
        "and write the report (with its confidence intervals) again",
    )
    p.add_argument(
        "--tensorboard",
        metavar="DIR",
        help="write the live TensorBoard curves of every run trained to DIR/NAME (default: "
        "none, as the checkpoints under OUT are meant to be committed)",
    )
    add_connection_arguments(p)
    p.set_defaults(func=_cmd_paper)

    p = sub.add_parser(
        "recipe",
        help="the best learned policy's whole recipe for one training seed: DAgger from the "
        "planner with memory features, then PPO from it (docs/agents.md)",
        formatter_class=DefaultsHelpFormatter,
    )
    p.add_argument("--out", required=True, help="directory of the two stages' checkpoints")
    p.add_argument("--seed", type=int, default=0, help="training seed of both stages")
    p.add_argument(
        "--ppo-steps",
        type=int,
        default=PPO_STEPS,
        help="environment steps of the PPO stage (a stopped run is resumed to them)",
    )
    add_connection_arguments(p)
    p.set_defaults(func=_cmd_recipe)

    p = sub.add_parser(
        "bench-ppo",
        help="PPO's end-to-end env-steps/s and where an iteration's time goes",
        formatter_class=DefaultsHelpFormatter,
    )
    p.add_argument(
        "--algorithm",
        choices=["ppo-masked", "ppo", "ppo-kickstart"],
        default="ppo-masked",
        help="ppo-kickstart: the recipe's PPO stage, from --init",
    )
    p.add_argument(
        "--init",
        metavar="DIR",
        help="ppo-kickstart: the DAgger checkpoint (with memory) it starts from",
    )
    p.add_argument("--num-envs", type=int, default=256, help="environments stepped together")
    p.add_argument(
        "--iterations", type=int, default=10, help="timed iterations (after one that compiles)"
    )
    p.add_argument(
        "--pipeline",
        type=int,
        default=PIPELINE,
        help="vector envs the environments are split into, stepped in turn (1: no overlap; "
        f"default {PIPELINE}, as train)",
    )
    p.add_argument("--json", action="store_true", help="also print the figures as JSON")
    add_connection_arguments(p)
    p.set_defaults(func=_cmd_bench_ppo)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    from .errors import AgentsError

    return run_command(_parser().parse_args(argv), (AgentsError,))

"""The paper's experiment end to end (``python -m dinerdash_agents paper --out docs/results``):
collect the 274 expert demonstrations (seeds 0..273), train every agent on the first 274 and the
first 70 episodes, evaluate each, the random policy and the expert on the 100 unseen seeds
1000..1099, and write ``results.md``, ``results.json``, ``results.png`` (Fig. 5's bars, paper
beside ours) and the checkpoints under ``checkpoints/<name>/``."""

from __future__ import annotations

import json
import os
import platform
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from . import checkpoint
from .connect import ConnectOptions, options, served
from .dagger import DaggerConfig
from .evaluate import evaluate_policy
from .kickstart import KickstartConfig
from .train_dagger import train_dagger
from .train_imitation import default_config, train_checkpoint
from .train_rl import RL, RL_ALGORITHMS, train_rl

__all__ = ["AGENTS", "EVAL_EPISODES", "EVAL_SEED", "run_paper"]

DEMO_EPISODES = 274
EVAL_SEED = 1000
EVAL_EPISODES = 100
#: Fig. 5 of the paper (average score over 100 episodes) and its expert.
PAPER_EXPERT = 9921.0
PAPER_RANDOM = -1245.8


@dataclass(frozen=True)
class Agent:
    name: str
    algorithm: str
    episodes: int  # demonstrations used (0: none, RL on the game's reward)
    loss: str  # imitation agents: "masked" or "plain"; RL agents: "masked" or "unmasked" policy
    paper: float | None  # the paper's Fig. 5 value, where it has one
    #: Whose demonstrations: the reference "expert" (the paper's), or the look-ahead "planner"
    #: (beyond the paper).
    teacher: str = "expert"
    #: Training seeds (runs): seed k > 0's checkpoint is ``checkpoints/<name>-seed<k>``.
    training_seeds: int = 1
    #: Kick-started PPO: the agent whose checkpoint of the same training seed its actor starts
    #: from.
    start: str = ""

    def directory(self, out: Path, k: int) -> Path:
        """The checkpoint of training seed ``k`` (``seed + k``) under the results ``out``."""
        return out / "checkpoints" / (self.name if k == 0 else f"{self.name}-seed{k}")

    @property
    def rl(self) -> bool:
        return self.algorithm in RL_ALGORITHMS

    @property
    def label(self) -> str:
        return _LABELS[self.algorithm](self)


def _imitation_label(agent: Agent) -> str:
    loss = "plain cross-entropy" if agent.loss == "plain" else "cross-entropy over legal actions"
    what = {"bc": "BC", "dpgm": "DPGM"}[agent.algorithm]
    demos = "demos" if agent.teacher == "expert" else "planner demos (beyond the paper)"
    return f"{what}, {agent.episodes} {demos}, {loss}"


def _ppo_label(agent: Agent) -> str:
    return f"PPO, policy {'over legal actions' if agent.loss == 'masked' else 'over all 57'}"


def _dagger_label(agent: Agent) -> str:
    settings = DAGGER_SETTINGS.get(agent.name, {})
    memory = (
        ", the learner remembering how long each patience level has lasted"
        if settings.get("memory")
        else ""
    )
    if settings.get("patience"):
        memory += " and each group's exact patience"
    if settings.get("learner_memory") == "own":
        memory += ", its memory told its own choices where the teacher acted"
    return f"DAgger, the {agent.teacher} labelling the learner's states{memory} (beyond the paper)"


def _recurrent_label(agent: Agent) -> str:
    settings = RECURRENT_SETTINGS.get(agent.name, {})
    memory = " and the hand-made memory features" if settings.get("memory") else ""
    what = (
        f"an MLP over the last {settings.get('stack', 8)} observations{memory} "
        "(frame-stacked baseline)"
        if settings.get("kind") == "stack"
        else f"a GRU over the episode's observations{memory}"
    )
    budget = ", ".join(
        template.format(settings[key])
        for key, template in (
            ("episodes_per_round", "{:g} episodes a round"),
            ("epochs", "{:g} epochs"),
            ("seat_weight", "seat weight {:g}"),
        )
        if key in settings
    )
    budget = f" ({budget})" if budget else ""
    return f"DAgger, the {agent.teacher} labelling the states of {what}{budget} (beyond the paper)"


def _kickstart_label(agent: Agent) -> str:
    settings = KICKSTART_SETTINGS.get(agent.name, {})
    if settings.get("kick_coef") != 0:
        return (
            f"masked PPO kick-started from `{agent.start}`, pulled toward the {agent.teacher}'s "
            "actions (beyond the paper)"
        )
    critic = ", its critic reading them too" if settings.get("critic_memory") else ""
    if settings.get("critic_lives"):
        critic += " and the groups lost"
    if settings.get("actor_lives"):
        critic += ", the actor counting them from what it sees"
    return (
        f"masked PPO from `{agent.start}`'s policy, its memory features kept, on the game's "
        f"reward alone{critic} (beyond the paper)"
    )


#: Each algorithm's row label in the table.
_LABELS = {
    "bc": _imitation_label,
    "dpgm": _imitation_label,
    "ppo": _ppo_label,
    "ppo-masked": _ppo_label,
    "gail": lambda a: f"GAIL (masked PPO on a discriminator's reward), {a.episodes} demos",
    "ppo-kickstart": _kickstart_label,
    "dagger": _dagger_label,
    "dagger-recurrent": _recurrent_label,
}


#: Training seeds of the agents that train in seconds (``paper`` trains them all), and of the
#: long runs (committed checkpoints ``paper`` loads).
FAST_SEEDS = 5
LONG_SEEDS = 3

#: The kick-started rows from the DAgger learner with memory: everything after their names.
_FROM_MEMORY_LEARNER = (
    "ppo-kickstart",
    0,
    "masked",
    None,
    "expert",
    LONG_SEEDS,
    "dagger-planner-memory",
)

AGENTS = [
    Agent("dpgm-274", "dpgm", 274, "masked", 9608.1, training_seeds=FAST_SEEDS),
    Agent("bc-274", "bc", 274, "masked", 7791.2, training_seeds=FAST_SEEDS),
    Agent("bc-plain-274", "bc", 274, "plain", 7791.2, training_seeds=FAST_SEEDS),
    Agent("dpgm-70", "dpgm", 70, "masked", 7064.3, training_seeds=FAST_SEEDS),
    Agent("bc-70", "bc", 70, "masked", 6343.8, training_seeds=FAST_SEEDS),
    Agent("bc-plain-70", "bc", 70, "plain", 6343.8, training_seeds=FAST_SEEDS),
    Agent("bc-planner-274", "bc", 274, "masked", None, "planner", FAST_SEEDS),
    Agent("dpgm-planner-274", "dpgm", 274, "masked", None, "planner", FAST_SEEDS),
    Agent("ppo-masked", "ppo-masked", 0, "masked", 8799.1, training_seeds=LONG_SEEDS),
    Agent("ppo", "ppo", 0, "unmasked", 8799.1, training_seeds=LONG_SEEDS),
    Agent("gail-274", "gail", 274, "masked", 8254.4, training_seeds=LONG_SEEDS),
    Agent("ppo-kickstart", "ppo-kickstart", 274, "masked", None, "expert", LONG_SEEDS, "bc-274"),
    Agent("dagger-planner", "dagger", 0, "masked", None, "planner", LONG_SEEDS),
    Agent("dagger-expert", "dagger", 0, "masked", None, "expert", LONG_SEEDS),
    Agent("dagger-planner-memory", "dagger", 0, "masked", None, "planner", LONG_SEEDS),
    Agent("ppo-kickstart-memory", *_FROM_MEMORY_LEARNER),
    Agent("ppo-kickstart-critic", *_FROM_MEMORY_LEARNER),
    Agent("ppo-kickstart-lives", *_FROM_MEMORY_LEARNER),
    Agent("ppo-kickstart-actor-lives", *_FROM_MEMORY_LEARNER),
    Agent("dagger-planner-own-memory", "dagger", 0, "masked", None, "planner", LONG_SEEDS),
    # The same as those, started from another DAgger learner.
    Agent("ppo-kickstart-own-memory", *_FROM_MEMORY_LEARNER[:-1], "dagger-planner-own-memory"),
    Agent("dagger-gru", "dagger-recurrent", 0, "masked", None, "planner", LONG_SEEDS),
    Agent("dagger-stack", "dagger-recurrent", 0, "masked", None, "planner"),
    Agent("dagger-gru-w10", "dagger-recurrent", 0, "masked", None, "planner", LONG_SEEDS),
    Agent("dagger-stack-w10", "dagger-recurrent", 0, "masked", None, "planner", LONG_SEEDS),
]
#: The DAgger rows' settings beyond :class:`~dinerdash_agents.dagger.DaggerConfig`'s defaults
#: (docs/agents.md says why the planner's seat states weigh 10).
DAGGER_SETTINGS: dict[str, dict[str, Any]] = {
    "dagger-planner": {"rounds": 12, "seat_weight": 10.0},
    "dagger-expert": {"rounds": 8, "seat_weight": 1.0},
    "dagger-planner-memory": {"rounds": 12, "seat_weight": 4.0, "memory": True},
    # Exact patience too, the learner's own memory told its choices (issue 49: docs/agents.md).
    "dagger-planner-own-memory": {
        "rounds": 12,
        "seat_weight": 4.0,
        "memory": True,
        "patience": True,
        "learner_memory": "own",
    },
}
#: The recurrent and frame-stacked DAgger rows' settings beyond
#: :class:`~dinerdash_agents.recurrent.RecurrentConfig`'s defaults.
RECURRENT_SETTINGS: dict[str, dict[str, Any]] = {
    "dagger-gru": {"kind": "gru", "hidden": 256, "rounds": 4},
    "dagger-stack": {"kind": "stack", "stack": 8, "hidden": 256, "rounds": 4},
    # Twice the episodes a round, a third of the epochs (the GRU above memorised its training
    # episodes), seat weight 10: chosen on seeds 2000..2049 (7,934 against 6,055).
    "dagger-gru-w10": {
        "kind": "gru",
        "hidden": 256,
        "rounds": 4,
        "episodes_per_round": 128,
        "epochs": 2,
        "seat_weight": 10.0,
    },
    # The frame-stacked baseline at dagger-gru-w10's budget.
    "dagger-stack-w10": {
        "kind": "stack",
        "stack": 8,
        "hidden": 256,
        "rounds": 4,
        "episodes_per_round": 128,
        "epochs": 2,
        "seat_weight": 10.0,
    },
}
#: Environment steps of the RL agents: the paper's PPO budget, and the others' by name.
RL_STEPS = 30_000_000
STEPS = {
    "gail-274": 10_000_000,
    "ppo-kickstart": RL_STEPS,
    "ppo-kickstart-memory": 20_000_000,
    "ppo-kickstart-critic": 20_000_000,
    "ppo-kickstart-lives": 20_000_000,
    "ppo-kickstart-actor-lives": 20_000_000,
    "ppo-kickstart-own-memory": 20_000_000,
}
#: Kick-started rows' settings beyond :class:`~dinerdash_agents.kickstart.KickstartConfig`'s
#: defaults: from the DAgger learner with memory, no pull toward a teacher (its pull would be
#: toward the expert, whose play the planner's pupil does not follow; the planner as teacher
#: costs the server a look-ahead at every step); chosen on seeds 2000..2099, as was the critic
#: that reads the memory features too, 256 wide (issue 49), the groups lost, and the actor counting
#: them from its observations (both on 2000..2399).
_CRITIC = {"kick_coef": 0.0, "critic_memory": True, "hidden": 256}
_ACTOR_LIVES = {**_CRITIC, "critic_lives": True, "actor_lives": True}
KICKSTART_SETTINGS: dict[str, dict[str, Any]] = {
    "ppo-kickstart-memory": {"kick_coef": 0.0},
    "ppo-kickstart-critic": _CRITIC,
    "ppo-kickstart-lives": {**_CRITIC, "critic_lives": True},
    "ppo-kickstart-actor-lives": _ACTOR_LIVES,
    # The same stage from the learner whose memory was told its own choices.
    "ppo-kickstart-own-memory": _ACTOR_LIVES,
}


def run_paper(
    out: str | Path,
    *,
    address: str | list[str] | None = None,
    connect: ConnectOptions | None = None,
    demos: str | Path | None = None,
    seed: int = 0,
    rl_steps: int | None = None,
    update: bool = False,
    tensorboard: str | Path | None = None,
    **connection: Any,
) -> dict[str, Any]:
    """Runs the experiment against the server(s) of ``connect`` (with ``address`` and the
    connection keywords put in; none named: ``DINERDASH_ADDRESS``, else a local server started
    here) and writes its results under ``out``; returns them. ``demos``: the
    expert's demonstrations to use instead of collecting them; ``rl_steps``: every RL agent's
    budget instead of the paper's; ``update``: keep the rows (and the expert's, planner's and
    random play's) of ``out/results.json`` and only train and evaluate the agents it lacks, then
    write the report again; ``tensorboard``: a directory for the live curves of every run trained
    (``<tensorboard>/<checkpoint name>``; ``None``: none written); ``connection``: the connection
    keywords of every env (``timeout``, ``tls``, ``tls_ca``, ...)."""
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    previous = None
    if update and (out / "results.json").is_file():
        previous = json.loads((out / "results.json").read_text())
    if previous is not None and all(_done(agent, previous) for agent in AGENTS):
        return _write(out, previous)
    # A local server, if any, starts before any JAX work.
    connect = options(connect, "run_paper", address, **connection)
    with served(connect) as (connect, _):
        with tempfile.TemporaryDirectory(prefix="dinerdash-demos-") as tmp:
            if previous is not None:
                # Only agents missing from the previous results are trained: the demonstrations
                # are collected only if one of them needs them.
                needs = {a.teacher for a in AGENTS if not _done(a, previous) and a.episodes > 0}
            else:
                needs = {"expert", "planner"}
            if demos is None and "expert" in needs:
                demos = _collect(Path(tmp), connect, "expert")
            planner_demos = (
                _collect(Path(tmp), connect, "planner")
                if "planner" in needs
                else Path("dinerdash_planner.npz")
            )
            return _experiment(
                out,
                Path(demos or "dinerdash_expert.npz"),
                planner_demos,
                connect,
                seed,
                rl_steps,
                previous,
                None if tensorboard is None else Path(tensorboard),
            )


def _collect(directory: Path, connect: ConnectOptions, policy: str) -> Path:
    """The ``policy``'s demonstrations of seeds 0..273, as ``python -m dinerdash collect``
    writes them."""
    from dinerdash.evaluation import Progress, collect

    progress = Progress(DEMO_EPISODES, f"collect {policy}")
    collected = collect(
        directory,
        policy=policy,
        episodes=DEMO_EPISODES,
        seed=0,
        connect=connect,
        progress=progress,
    )
    progress.close()
    print(f"wrote {collected.path}: {DEMO_EPISODES} episodes, {collected.steps} steps")
    return collected.path


def _experiment(
    out: Path,
    demos: Path,
    planner_demos: Path,
    connect: ConnectOptions,
    seed: int,
    rl_steps: int | None,
    previous: dict[str, Any] | None = None,
    tensorboard: Path | None = None,
) -> dict[str, Any]:
    from dinerdash.evaluation import Progress, evaluate_through_env

    rows: list[dict[str, Any]] = []

    def evaluate(name: str, fn) -> dict[str, Any]:
        progress = Progress(EVAL_EPISODES, f"evaluate {name}")
        scores, lengths = fn(progress)
        progress.close()
        return {
            "scores": [int(s) for s in scores],
            "lengths": [int(x) for x in lengths],
            "mean": float(np.mean(scores)),
            "sd": float(np.std(scores)),
            "mean_length": float(np.mean(lengths)),
        }

    common = {"seed": EVAL_SEED, "connect": connect, "num_envs": EVAL_EPISODES}
    if previous is not None:
        expert, random, planner = previous["expert"], previous["random"], previous["planner"]
    else:
        expert = evaluate(
            "expert", lambda p: evaluate_through_env("expert", EVAL_EPISODES, progress=p, **common)
        )
        random = evaluate(
            "random", lambda p: evaluate_through_env("random", EVAL_EPISODES, progress=p, **common)
        )
        planner = evaluate(
            "planner",
            lambda p: evaluate_through_env("planner", EVAL_EPISODES, progress=p, **common),
        )
    job = _Job(
        out,
        demos,
        planner_demos,
        connect,
        seed,
        rl_steps,
        reuse=previous is not None,
        tensorboard=tensorboard,
    )
    for agent in AGENTS:
        if previous is not None and _done(agent, previous):
            rows.extend(r for r in previous["agents"] if r["name"].split(" (")[0] == agent.name)
            continue
        rows.extend(_agent_rows(agent, job, evaluate, common))
    results = {
        "command": "python -m dinerdash_agents paper --out docs/results",
        "demonstrations": {
            "file": demos.name,
            "planner_file": planner_demos.name,
            "seeds": f"0..{DEMO_EPISODES - 1}",
        },
        "evaluation": {"seeds": f"{EVAL_SEED}..{EVAL_SEED + EVAL_EPISODES - 1}"},
        "machine": {
            "cores": os.cpu_count(),
            "python": platform.python_version(),
            # Other work on the machine slows the wall-clock training times down.
            "load_average_at_end": [round(x, 2) for x in os.getloadavg()],
        },
        "date_utc": time.strftime("%Y-%m-%d %H:%M", time.gmtime()),
        "expert": expert,
        "random": {**random, "paper": PAPER_RANDOM, "fraction": random["mean"] / expert["mean"]},
        "planner": {**planner, "fraction": planner["mean"] / expert["mean"]},
        "agents": rows,
    }
    if previous is not None:
        results["date_utc"] = previous["date_utc"]
        results["machine"] = previous["machine"]
        results["updated_utc"] = time.strftime("%Y-%m-%d %H:%M", time.gmtime())
    return _write(out, results)


def _done(agent: Agent, previous: dict[str, Any]) -> bool:
    """Whether ``previous`` results hold ``agent``'s row with all its training seeds."""
    row = next((r for r in previous["agents"] if r["name"] == agent.name), None)
    return row is not None and len(_runs(row)) == agent.training_seeds


#: Pairs of rows whose difference the report gives with its paired interval (A, B, what A
#: has that B lacks).
COMPARISONS = [
    ("dpgm-274", "bc-274", "DPGM's factored policy, 274 demos"),
    ("dpgm-70", "bc-70", "DPGM's factored policy, 70 demos"),
    ("ppo-kickstart", "ppo-masked", "the kick-start from BC"),
    ("dagger-planner-memory", "dagger-planner", "the hand-made memory features"),
    ("dagger-gru-w10", "dagger-stack-w10", "the recurrence, at the same budget"),
    ("ppo-kickstart-memory", "dagger-planner-memory", "PPO on the game's reward after DAgger"),
    ("ppo-kickstart-memory", "ppo-kickstart", "the memory features, both PPO from imitation"),
    ("ppo-kickstart-critic", "ppo-kickstart-memory", "the critic reading the memory features"),
    ("ppo-kickstart-lives", "ppo-kickstart-critic", "the critic reading the groups lost too"),
    ("ppo-kickstart-actor-lives", "ppo-kickstart-lives", "the actor counting the groups lost"),
    (
        "dagger-planner-own-memory",
        "dagger-planner-memory",
        "exact patience, the learner's memory told its own choices",
    ),
    (
        "ppo-kickstart-own-memory",
        "ppo-kickstart-actor-lives",
        "PPO's start: the DAgger learner whose memory was told its own choices",
    ),
]


def _runs(row: dict[str, Any]) -> list[list[int]]:
    return row.get("runs") or [row["scores"]]


def _add_stats(results: dict[str, Any]) -> None:
    """Every row's (and the planner's and random play's) :mod:`~dinerdash_agents.stats`
    against the expert's scores on the same seeds: pooled over the row's training seeds
    (``runs``, else its one run's ``scores``); and the paired differences of
    :data:`COMPARISONS`."""
    from .stats import agent_stats, difference_interval

    expert = results["expert"]["scores"]
    for row in [results["planner"], results["random"], *results["agents"]]:
        row["stats"] = agent_stats(_runs(row), expert).to_json()
        row["fraction"] = row["stats"]["fraction"]
    by = {row["name"]: row for row in results["agents"]}
    results["differences"] = [
        {
            "a": a,
            "b": b,
            "what": what,
            **dict(
                zip(
                    ("difference", "low", "high"),
                    difference_interval(_runs(by[a]), _runs(by[b]), expert),
                    strict=True,
                )
            ),
        }
        for a, b, what in COMPARISONS
        if a in by and b in by
    ]


def _write(out: Path, results: dict[str, Any]) -> dict[str, Any]:
    _add_stats(results)
    (out / "results.json").write_text(json.dumps(results, indent=1) + "\n")
    (out / "results.md").write_text(_markdown(results))
    _figure(results, out / "results.png")
    print(f"wrote {out / 'results.md'}, {out / 'results.json'}, {out / 'results.png'}")
    print((out / "results.md").read_text())
    return results


@dataclass(frozen=True)
class _Job:
    """What every agent's training shares: the results directory, both demonstration files, the
    server(s), the base training seed, the RL budget, whether checkpoints that stand are
    reused (``--update``) rather than trained again, and where the live curves go (``None``:
    nowhere)."""

    out: Path
    demos: Path
    planner_demos: Path
    connect: ConnectOptions
    seed: int
    rl_steps: int | None
    reuse: bool
    tensorboard: Path | None = None

    def curves(self, directory: Path) -> Path | None:
        """The live curves' directory of the run checkpointed to ``directory``."""
        return None if self.tensorboard is None else self.tensorboard / directory.name


def _agent_rows(agent: Agent, job: _Job, evaluate, common) -> list[dict[str, Any]]:
    """The agent's rows (one, or two for the plain-loss and unmasked agents: their policy also
    played greedily over all 57 actions): each training seed's checkpoint trained (or loaded)
    and evaluated; ``runs`` holds every seed's scores, ``scores`` seed 0's."""
    masks = [True, False] if agent.loss in ("plain", "unmasked") else [True]
    names = {m: agent.name + ("" if m else " (no mask)") for m in masks}
    results: dict[bool, list[dict[str, Any]]] = {m: [] for m in masks}
    descriptions = []
    for k in range(agent.training_seeds):
        policy, description = _RUNS.get(agent.algorithm, _train_rl)(agent, job, k)
        descriptions.append(description)
        for use_mask in masks:
            name = names[use_mask]
            results[use_mask].append(
                evaluate(
                    name if agent.training_seeds == 1 else f"{name} seed {k}",
                    lambda p, m=use_mask, act=policy.act: evaluate_policy(
                        act, EVAL_EPISODES, progress=p, use_mask=m, **common
                    ),
                )
            )
    d0 = descriptions[0]
    rows = []
    for use_mask in masks:
        runs = results[use_mask]
        rows.append(
            {
                "name": names[use_mask],
                "label": agent.label + ("" if use_mask else ", greedy over all 57"),
                "algorithm": agent.algorithm,
                "episodes": agent.episodes,
                "loss": agent.loss,
                "greedy_over": "legal actions" if use_mask else "all 57 actions",
                "paper": agent.paper,
                "paper_fraction": None if agent.paper is None else agent.paper / PAPER_EXPERT,
                "fraction": None,  # the runs' mean over the expert's: see _add_stats
                "training_seconds": float(
                    np.mean([d["training"]["seconds"] for d in descriptions])
                ),
                "training_cpu_seconds": float(
                    np.mean([d["training"]["cpu_seconds"] for d in descriptions])
                ),
                "training_steps": d0["data"].get("steps"),
                "environment_steps": d0["data"].get("environment_steps"),
                **runs[0],
                **(
                    {"runs": [r["scores"] for r in runs], "run_means": [r["mean"] for r in runs]}
                    if len(runs) > 1
                    else {}
                ),
            }
        )
    return rows


def _standing(directory: Path) -> bool:
    return (directory / checkpoint.DESCRIPTION).is_file()


def _loaded(directory: Path) -> tuple[Any, dict[str, Any]]:
    return checkpoint.load(directory), checkpoint.read_description(directory)


def _train_imitation(agent: Agent, job: _Job, k: int) -> tuple[Any, dict[str, Any]]:
    """Trains training seed ``k`` of an imitation agent on the first ``agent.episodes`` of its
    teacher's demonstrations (seconds); with ``job.reuse``, a checkpoint that stands is loaded."""
    directory = agent.directory(job.out, k)
    if job.reuse and _standing(directory):
        return _loaded(directory)
    return train_checkpoint(
        agent.algorithm,
        job.demos if agent.teacher == "expert" else job.planner_demos,
        directory,
        episodes=agent.episodes,
        seed=job.seed + k,
        config=default_config(agent.algorithm, loss=agent.loss),
        name=directory.name,
        tensorboard=job.curves(directory),
    )


def _train_rl(agent: Agent, job: _Job, k: int) -> tuple[Any, dict[str, Any]]:
    """Trains training seed ``k`` of an RL agent, or continues its run where a checkpoint of it
    already stands (a finished run is only loaded: the full budgets take tens of minutes).
    A kick-started one starts from its start agent's checkpoint of the same training seed."""
    directory = agent.directory(job.out, k)
    steps = job.rl_steps or STEPS.get(agent.name, RL_STEPS)
    resume = directory if _standing(directory) else None
    # Kick-started PPO starts from a checkpoint, with a teacher.
    kickstart = RL[agent.algorithm].start is not None and resume is None
    train_rl(
        agent.algorithm,
        steps,
        directory,
        connect=job.connect,
        demos=job.demos if RL[agent.algorithm].needs_demos else None,
        seed=job.seed + k,
        resume=resume,
        init=_start_of(agent).directory(job.out, k) if kickstart else None,
        teacher=agent.teacher if kickstart else None,
        config=KickstartConfig(**KICKSTART_SETTINGS[agent.name])
        if kickstart and agent.name in KICKSTART_SETTINGS
        else None,
        tensorboard=job.curves(directory),
    )
    return _loaded(directory)


def _start_of(agent: Agent) -> Agent:
    """The agent a kick-started one starts from."""
    return next(a for a in AGENTS if a.name == agent.start)


def _train_taught(agent: Agent, job: _Job, k: int) -> tuple[Any, dict[str, Any]]:
    """Runs training seed ``k`` of a DAgger agent with its teacher (a feed-forward learner with
    :data:`DAGGER_SETTINGS`, a recurrent or frame-stacked one with :data:`RECURRENT_SETTINGS`),
    or only loads a checkpoint of it that already stands (the planner's rounds take minutes)."""
    from .recurrent import RecurrentConfig

    directory = agent.directory(job.out, k)
    if not _standing(directory):
        config = (
            DaggerConfig(teacher=agent.teacher, **DAGGER_SETTINGS[agent.name])
            if agent.name in DAGGER_SETTINGS
            else RecurrentConfig(teacher=agent.teacher, **RECURRENT_SETTINGS[agent.name])
        )
        train_dagger(
            directory,
            config,
            connect=job.connect,
            seed=job.seed + k,
            name=directory.name,
            tensorboard=job.curves(directory),
        )
    return _loaded(directory)


#: How each agent's policy is had, by algorithm (the RL ones: :func:`_train_rl`).
_RUNS = {
    "bc": _train_imitation,
    "dpgm": _train_imitation,
    "dagger": _train_taught,
    "dagger-recurrent": _train_taught,
}


def _pct(x: float | None) -> str:
    return "" if x is None else f"{100 * x:.1f} %"


def _ours(row: dict[str, Any]) -> str:
    """The columns "ours (mean ± sd)", "ours / expert [95 % interval]", "IQM" and "runs"."""
    st = row["stats"]
    mean = f"{st['mean']:,.1f} ± {row['sd']:,.1f}"
    interval = f"{_pct(st['fraction'])} [{_pct(st['fraction_low'])}, {_pct(st['fraction_high'])}]"
    runs = str(st["runs"])
    if st["runs"] > 1:
        runs += " (" + ", ".join(_pct(f) for f in st["run_fractions"]) + ")"
    return f"{mean} | {interval} | {st['iqm']:,.1f} | {runs}"


def _markdown(r: dict[str, Any]) -> str:
    from .stats import iqm

    e = r["expert"]
    updated = f" (rows added on {r['updated_utc']} UTC)" if r.get("updated_utc") else ""
    lines = [
        "# The paper's Fig. 5, reproduced",
        "",
        f"Written by `{r['command']}` on {r['date_utc']} UTC{updated} "
        f"({r['machine']['cores']} cores). "
        f"Demonstrations: expert episodes of seeds {r['demonstrations']['seeds']} (the first 274 "
        "or the first 70 of them; the planner's rows: the look-ahead planner's episodes of the "
        "same seeds). RL agents: PPO on the game's reward, GAIL on a discriminator's, "
        "kick-started PPO on the game's reward from BC's policy with a decaying pull toward the "
        "teacher's actions, or from the DAgger learner with memory without a pull; environment "
        "steps in the training column; DAgger: rounds of the "
        "learner's own episodes of training seeds, every state labelled by the planner or the "
        "expert (its states in that column). "
        f"Evaluation: {EVAL_EPISODES} unseen seeds "
        f"{r['evaluation']['seeds']}, greedy actions, final score per episode. Fractions are of "
        "the expert's mean on the same seeds (the paper's of its expert's 9,921), with a 95 % "
        "BCa bootstrap interval paired on the evaluation seeds (agent and expert resampled seed "
        "by seed, `scipy.stats.bootstrap`, 10,000 resamples; the training seeds are averaged, "
        "not resampled). IQM: the interquartile mean of all the agent's evaluation episodes. "
        "Runs: training seeds, each one's fraction in brackets when there are several; mean and "
        "fraction are over all of them (the sd is the first run's). Training: wall clock (the "
        "runs' mean), and CPU seconds of all threads in brackets; the 1-minute load average was "
        f"{r['machine']['load_average_at_end'][0]} at the end of the run.",
        "",
        "| agent | paper | paper / expert | ours (mean ± sd) | ours / expert [95 % interval] "
        "| IQM | runs | training |",
        "|---|---:|---:|---:|---:|---:|---:|---:|",
        f"| reference expert | {PAPER_EXPERT:,.1f} | 100.0 % | {e['mean']:,.1f} ± {e['sd']:,.1f} "
        f"| 100.0 % | {iqm(e['scores']):,.1f} | 1 | |",
        f"| look-ahead planner (beyond the paper) | | | {_ours(r['planner'])} | |",
    ]
    for row in r["agents"]:
        paper = "" if row["paper"] is None else f"{row['paper']:,.1f}"
        env_steps = row.get("environment_steps")
        steps = f", {env_steps:,} env steps" if env_steps else ""
        lines.append(
            f"| `{row['name']}`: {row['label']} | {paper} | {_pct(row['paper_fraction'])} "
            f"| {_ours(row)} "
            f"| {row['training_seconds']:.1f} s ({row['training_cpu_seconds']:.1f} s){steps} |"
        )
    lines.append(
        f"| random | {PAPER_RANDOM:,.1f} | {_pct(PAPER_RANDOM / PAPER_EXPERT)} "
        f"| {_ours(r['random'])} | |"
    )
    by = {row["name"]: row for row in r["agents"]}
    lines += ["", "Paper's ordering, DPGM above BC (both with the loss over legal actions):"]
    for k in (274, 70):
        d, b = by[f"dpgm-{k}"]["stats"], by[f"bc-{k}"]["stats"]
        verdict = "yes" if d["mean"] > b["mean"] else "no"
        lines.append(
            f"- {k} demonstrations: DPGM {d['mean']:,.1f} vs BC {b['mean']:,.1f}: {verdict}"
        )
    lines += [
        "",
        "Paired differences, A − B in percent of the expert's mean, with a 95 % BCa interval "
        "(A's, B's and the expert's scores resampled together seed by seed; each agent's runs "
        "averaged per seed):",
    ]
    for d in r["differences"]:
        lines.append(
            f"- `{d['a']}` − `{d['b']}` ({d['what']}): {100 * d['difference']:+.1f} points "
            f"[{100 * d['low']:+.1f}, {100 * d['high']:+.1f}]"
        )
    return "\n".join(lines) + "\n"


def _figure(r: dict[str, Any], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    names = ["expert", "planner"] + [row["name"] for row in r["agents"]] + ["random"]
    others = [r["planner"], *r["agents"], r["random"]]
    expert_mean = r["expert"]["mean"]
    ours = [expert_mean] + [row["stats"]["mean"] for row in others]
    # The paired 95 % intervals of the fraction of the expert, in points (the expert's own: none).
    low = [expert_mean] + [row["stats"]["fraction_low"] * expert_mean for row in others]
    high = [expert_mean] + [row["stats"]["fraction_high"] * expert_mean for row in others]
    xerr = np.array([np.subtract(ours, low), np.subtract(high, ours)]).clip(min=0)
    paper = [PAPER_EXPERT, None] + [row["paper"] for row in r["agents"]] + [PAPER_RANDOM]
    y = np.arange(len(names))[::-1]
    fig, ax = plt.subplots(figsize=(8, 0.55 * len(names) + 1.2), dpi=110)
    ax.barh(
        y + 0.2,
        ours,
        height=0.4,
        color="#3b7dd8",
        xerr=xerr,
        error_kw={"elinewidth": 1, "capsize": 2, "ecolor": "#1a3d6e"},
        label="ours (seeds 1000..1099), paired 95 % interval",
    )
    ax.barh(
        y - 0.2,
        [0 if p is None else p for p in paper],
        height=0.4,
        color="#bbbbbb",
        label="paper, Fig. 5",
    )
    for yi, v, h in zip(y, ours, high, strict=True):
        ax.text(max(v, h, 0) + 80, yi + 0.2, f"{v:,.0f}", va="center", fontsize=8)
    for yi, v in zip(y, paper, strict=True):
        if v is not None:
            ax.text(max(v, 0) + 80, yi - 0.2, f"{v:,.1f}", va="center", fontsize=8, color="#555")
    ax.set_yticks(y, names)
    ax.axvline(0, color="black", linewidth=0.8)
    ax.set_xlabel("average score over 100 episodes")
    ax.set_title("DinerDash: final performance (Fig. 5 style)")
    ax.set_xlim(min(min(ours), PAPER_RANDOM) - 500, max(max(high), PAPER_EXPERT) * 1.15)
    ax.legend(loc="lower right", fontsize=8)
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)

#!/usr/bin/env python3
"""A chaos run (``make chaos``): the project's masked PPO trains across three local servers while a
seeded monkey kills, hangs, black-holes, drains and restarts them.

Every 10-20 s (``random.Random(seed)``) the monkey picks a server and one of:

- ``kill``: ``SIGKILL``; a supervisor starts it again on its port 2-8 s later;
- ``hang``: ``SIGSTOP``, ``SIGCONT`` 2-8 s later;
- ``blackhole``: the :class:`~dinerdash.testing.FaultProxy` in front of it swallows every byte,
  healed 2-8 s later;
- ``drain``: ``SIGTERM`` (a planned stop); started again once it has exited;
- ``restart``: ``SIGTERM``, wait for it to exit, start again on its port (a rolling update).

Faults do not overlap: each is over before the next. The trainer (``reconnect=True``,
``failover_after``, ``timeout``) connects to the proxies. A step that raises is counted and
training goes on from fresh vector envs (the iteration under way is collected again). At the end
the script prints the steps, the exceptions, failovers, rejoins, moves (the vector env's counters
where it has them), truncated episodes, and the trained policy's score on fixed evaluation seeds;
with ``--undisturbed``, beside a run of the same seed and the same number of iterations with no
monkey. Exit status 1 when the trainer saw an exception, or the two scores differ by more than
twice the standard error of their difference.

    .venv/bin/python scripts/chaos.py --server target/release/dinerdash-server --duration 180 \\
        --undisturbed

The servers and the monkey live in a child process started before JAX: forking a process while
JAX's threads run is unsafe, and the monkey starts servers again and again.
"""

from __future__ import annotations

import argparse
import multiprocessing
import os
import random
import subprocess
import sys
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parent.parent
FAULTS = ("kill", "hang", "blackhole", "drain", "restart")
#: Seconds a restarted or drained server may take to exit before it is killed.
EXIT_TIMEOUT = 60.0


# --- the servers and the monkey: a child process ------------------------------------------------


def _log(began: float, message: str) -> None:
    print(f"[chaos {time.monotonic() - began:7.1f} s] {message}", flush=True)


def keeper(binary: str, seed: int, monkey: bool, server_flags: dict, pipe: Any) -> None:
    """Runs a LocalCluster(3) with a FaultProxy in front of each server; sends the proxies'
    addresses, then (``monkey``) injects faults from the message ``"go"`` until ``"stop"``; heals
    everything, sends the faults made, and closes everything on ``"close"``."""
    os.environ["DINERDASH_SERVER"] = binary
    from dinerdash.testing import FaultProxy, LocalCluster

    with LocalCluster(3, **server_flags) as cluster:
        proxies = [FaultProxy(a) for a in cluster.addresses]
        try:
            pipe.send([p.address for p in proxies])
            assert pipe.recv() == "go"
            stop = threading.Event()
            faults: list[tuple[float, str, int]] = []
            thread = None
            if monkey:
                thread = threading.Thread(
                    target=_monkey,
                    args=(cluster, proxies, random.Random(seed), stop, faults),
                )
                thread.start()
            assert pipe.recv() == "stop"
            stop.set()
            if thread is not None:
                thread.join()
            for i, proxy in enumerate(proxies):  # everything up for the evaluation
                proxy.heal()
                cluster.resume(i)
                if not cluster.is_running(i):
                    cluster.restart(i)
            pipe.send((faults, cluster.addresses))
            assert pipe.recv() == "close"
        finally:
            for proxy in proxies:
                proxy.close()


def _monkey(
    cluster: Any, proxies: list, rng: random.Random, stop: threading.Event, faults: list
):
    began = time.monotonic()
    while not stop.wait(rng.uniform(10.0, 20.0)):
        fault, i = rng.choice(FAULTS), rng.randrange(len(proxies))
        recover = rng.uniform(2.0, 8.0)
        faults.append((time.monotonic() - began, fault, i))
        _log(began, f"{fault} server {i} ({cluster.addresses[i]})")
        if fault == "kill":
            cluster.kill(i)
            stop.wait(recover)
            cluster.restart(i)
            _log(began, f"server {i} started again after {recover:.1f} s")
        elif fault == "hang":
            cluster.hang(i)
            stop.wait(recover)
            cluster.resume(i)
            _log(began, f"server {i} resumed after {recover:.1f} s")
        elif fault == "blackhole":
            proxies[i].blackhole()
            stop.wait(recover)
            proxies[i].heal()
            _log(began, f"server {i}'s network healed after {recover:.1f} s")
        elif fault == "drain":
            cluster.drain(i)
            try:
                cluster.wait(i, EXIT_TIMEOUT)
            except TimeoutError:
                cluster.kill(i)
            cluster.restart(i)
            _log(began, f"server {i} drained and started again")
        else:
            cluster.restart(i, wait_drain=True, drain_timeout=EXIT_TIMEOUT)
            _log(began, f"server {i} restarted")


# --- the trainer -------------------------------------------------------------------------------


@dataclass
class Tally:
    """What the trainer saw."""

    iterations: int = 0
    steps: int = 0
    seconds: float = 0.0
    exceptions: list[str] = field(default_factory=list)
    episodes: int = 0
    truncated: int = 0
    #: Episodes cut by a reconnect or a failover (``info["reconnected"]``).
    cut: int = 0
    failovers: int | None = None
    rejoins: int | None = None
    moves: int | None = None
    score: Any = None


def _counter(envs: list, name: str) -> int | None:
    """The sum of the vector envs' counter ``name`` (``None`` if they have none)."""
    values = [getattr(e.unwrapped, name, None) for e in envs]
    return None if any(v is None for v in values) else int(sum(values))


def _counting(envs: Any, tally: Tally) -> Any:
    """``envs`` with its steps' ended, truncated and cut episodes added to ``tally``."""
    from gymnasium.vector import VectorWrapper

    class Counting(VectorWrapper):
        def step(self, actions):
            result = self.env.step(actions)
            _, _, terminated, truncated, info = result
            tally.episodes += int((terminated | truncated).sum())
            tally.truncated += int(truncated.sum())
            if "reconnected" in info:
                tally.cut += int((info["reconnected"] & info["_reconnected"]).sum())
            return result

    return Counting(envs)


def train(
    addresses: list[str],
    args: argparse.Namespace,
    tally: Tally,
    *,
    duration: float | None = None,
    iterations: int | None = None,
) -> Any:
    """Masked PPO on ``addresses`` for ``duration`` seconds or ``iterations`` iterations; returns
    the trainer."""
    import dataclasses

    from dinerdash_agents import ppo
    from dinerdash_agents.train_rl import make_envs

    # No learning-rate annealing: the chaos run's length is known only at its end, and the
    # undisturbed run must follow the same schedule.
    config = ppo.PPOConfig(masked=True, num_envs=args.num_envs, anneal_lr=False)
    connection = {
        "reconnect": True,
        "failover_after": args.failover_after,
        "timeout": args.timeout,
        "reconnect_timeout": args.reconnect_timeout,
        # Over gRPC through the proxies: shared memory (the default on the servers' host) would
        # step past them, and the black holes would touch only the health checks.
        "transport": "grpc",
    }
    began = time.monotonic()
    envs: list = []
    trainer = None
    counted: dict[str, int] = {}

    def fresh() -> list:
        while True:
            try:
                return [
                    _counting(e, tally)
                    for e in make_envs(config, addresses, **connection)
                ]
            except Exception as e:  # noqa: BLE001  (every server down now: try again)
                tally.exceptions.append(f"opening the envs: {type(e).__name__}: {e}")
                print(f"[trainer] {tally.exceptions[-1]}", flush=True)
                time.sleep(1.0)

    def add_counters() -> None:
        for name in ("failovers", "rejoins", "moves"):
            value = _counter(envs, name)
            if value is not None:
                counted[name] = counted.get(name, 0) + value
        if _counter(envs, "failovers") is None:  # today's client: the servers given up
            lost = sum(len(e.unwrapped.lost_addresses) for e in envs)
            counted["failovers"] = counted.get("failovers", 0) + lost

    def done() -> bool:
        if iterations is not None:
            return trainer.iteration >= iterations
        return time.monotonic() - began >= duration

    try:
        envs = fresh()
        if config.observation_high is None:
            high = envs[0].single_observation_space.high
            config = dataclasses.replace(config, observation_high=tuple(high.tolist()))
        trainer = ppo.Trainer(config, 10**12, seed=args.seed)
        trainer.attach(envs)
        while not done():
            try:
                trainer.step()
            except Exception as e:  # noqa: BLE001  (counted; training goes on)
                tally.exceptions.append(f"{type(e).__name__}: {e}")
                print(
                    f"[trainer] iteration {trainer.iteration}: {tally.exceptions[-1]}",
                    flush=True,
                )
                add_counters()
                for env in envs:
                    env.close()
                envs = fresh()
                trainer.attach(envs)
                continue
            if trainer.iteration % 10 == 0:
                print(
                    f"[trainer] {time.monotonic() - began:6.1f} s: iteration {trainer.iteration}, "
                    f"{trainer.steps:,} steps, mean score {trainer.mean_recent_score:,.0f}",
                    flush=True,
                )
        add_counters()
    finally:
        for env in envs:
            env.close()
    tally.seconds = time.monotonic() - began
    tally.iterations, tally.steps = trainer.iteration, trainer.steps
    tally.failovers = counted.get("failovers")
    tally.rejoins, tally.moves = counted.get("rejoins"), counted.get("moves")
    return trainer


def evaluate(trainer: Any, address: str, args: argparse.Namespace) -> Any:
    """The greedy policy's final scores on the fixed seeds ``eval_seed`` .. + ``eval_episodes``."""
    from dinerdash_agents.checkpoint import Policy
    from dinerdash_agents.evaluate import evaluate_policy

    policy = Policy(trainer.model, {"algorithm": "ppo-masked"})
    scores, _ = evaluate_policy(
        policy.act,
        args.eval_episodes,
        seed=args.eval_seed,
        address=address,
        num_envs=min(64, args.eval_episodes),
        max_steps=trainer.config.max_episode_steps,
    )
    return scores


def run(
    args: argparse.Namespace, monkey: bool, iterations: int | None = None
) -> tuple[Tally, list]:
    """One run on its own servers: a child process keeps them (and the monkey)."""
    context = multiprocessing.get_context("spawn")
    parent, child = context.Pipe()
    flags = (
        {"drain_timeout": f"{args.drain_timeout:g}"}
        if _supports_drain(args.server)
        else {}
    )
    process = context.Process(
        target=keeper, args=(args.server, args.seed, monkey, flags, child), daemon=True
    )
    process.start()
    tally, faults = Tally(), []
    try:
        proxies = parent.recv()
        parent.send("go")
        try:
            if iterations is None:
                trainer = train(proxies, args, tally, duration=args.duration)
            else:
                trainer = train(proxies, args, tally, iterations=iterations)
        finally:
            parent.send("stop")
            faults, servers = parent.recv()
        tally.score = evaluate(trainer, servers[0], args)
        parent.send("close")
    finally:
        process.join(timeout=60)
        if process.is_alive():
            process.terminate()
            process.join()
    return tally, faults


def _supports_drain(binary: str) -> bool:
    """Whether the server has ``--drain-timeout`` (issue 26's draining)."""
    shown = subprocess.run(
        [binary, "--help"], check=False, capture_output=True, text=True, timeout=30
    )
    return "--drain-timeout" in shown.stdout


def report(name: str, tally: Tally, faults: list | None) -> None:
    import numpy as np

    scores = np.asarray(tally.score, dtype=np.float64)
    sem = scores.std(ddof=1) / np.sqrt(len(scores)) if len(scores) > 1 else float("nan")

    def shown(value: int | None) -> str:
        return "n/a (this client has no such counter)" if value is None else f"{value}"

    print(f"\n== {name} ==")
    print(
        f"  trained           {tally.iterations} iterations, {tally.steps:,} env steps, "
        f"{tally.seconds:.0f} s ({tally.steps / max(tally.seconds, 1e-9):,.0f} steps/s)"
    )
    if faults is not None:
        kinds = {k: sum(1 for _, f, _ in faults if f == k) for k in FAULTS}
        print(
            f"  faults            {len(faults)}: "
            + ", ".join(f"{k} {n}" for k, n in kinds.items())
        )
    print(f"  exceptions        {len(tally.exceptions)}")
    for text in tally.exceptions:
        print(f"                    - {text[:160]}")
    print(f"  failovers         {shown(tally.failovers)}")
    print(f"  rejoins           {shown(tally.rejoins)}")
    print(f"  moves             {shown(tally.moves)}")
    print(
        f"  episodes ended    {tally.episodes:,}, truncated {tally.truncated:,} "
        f"(cut by a reconnect or failover: {tally.cut:,})"
    )
    print(
        f"  final score       {scores.mean():,.1f} ± {sem:,.1f} (mean ± s.e., sd "
        f"{scores.std(ddof=1):,.1f}) over {len(scores)} evaluation episodes"
    )


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument(
        "--server",
        default=os.environ.get("DINERDASH_SERVER")
        or str(ROOT / "target" / "release" / "dinerdash-server"),
    )
    parser.add_argument(
        "--duration", type=float, default=180.0, help="seconds of chaos training"
    )
    parser.add_argument(
        "--seed", type=int, default=0, help="the monkey's and the trainer's seed"
    )
    parser.add_argument("--num-envs", type=int, default=96)
    parser.add_argument("--failover-after", type=float, default=2.0)
    parser.add_argument(
        "--timeout", type=float, default=10.0, help="each call's deadline"
    )
    parser.add_argument("--reconnect-timeout", type=float, default=30.0)
    parser.add_argument(
        "--drain-timeout",
        type=float,
        default=10.0,
        help="the servers' --drain-timeout, if they have it",
    )
    parser.add_argument("--eval-episodes", type=int, default=64)
    parser.add_argument("--eval-seed", type=int, default=10_000)
    parser.add_argument(
        "--undisturbed",
        action="store_true",
        help="also train the same seed, as many iterations, without the monkey",
    )
    args = parser.parse_args(argv)
    if not Path(args.server).is_file():
        parser.error(f"--server {args.server}: no such binary (make build-server)")

    chaos, faults = run(args, monkey=True)
    report("chaos", chaos, faults)
    failed = bool(chaos.exceptions)
    if args.undisturbed:
        calm, _ = run(args, monkey=False, iterations=chaos.iterations)
        report("undisturbed, same seed and iterations", calm, None)
        gap, noise = _difference(chaos.score, calm.score)
        within = abs(gap) <= 2 * noise
        print(
            f"\nchaos - undisturbed: {gap:+,.1f} (2 s.e. of the difference: {2 * noise:,.1f}): "
            + ("within the noise" if within else "OUTSIDE the noise")
        )
        failed = failed or not within
    print(f"exceptions: {len(chaos.exceptions)}; " + ("FAILED" if failed else "passed"))
    return 1 if failed else 0


def _difference(a: Any, b: Any) -> tuple[float, float]:
    """The difference of the mean scores and its standard error."""
    import numpy as np

    a, b = np.asarray(a, dtype=np.float64), np.asarray(b, dtype=np.float64)
    se = np.sqrt(a.var(ddof=1) / len(a) + b.var(ddof=1) / len(b))
    return float(a.mean() - b.mean()), float(se)


if __name__ == "__main__":
    sys.exit(main())

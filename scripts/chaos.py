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
where it has them), truncated episodes, and the trained policy's scores on fixed evaluation seeds;
with ``--undisturbed``, beside a run of the same seed and the same number of iterations with no
monkey.

The judge (:func:`judge`, exit status 1 when it finds anything):

- the fault thread died (an exception in it is caught and reported), a fault it began did not end,
  or a fault it had scheduled before the stop never began: fewer faults than scheduled;
- an episode was cut (``info["reconnected"]``) while the last fault begun was a ``drain`` or a
  ``restart`` (planned stops move sessions whole by Snapshot and Restore: only crashes may cut),
  or with no fault begun at all;
- either run raised an exception;
- the score: each run's policy is kept at its last ``--snapshots`` multiples of
  ``--snapshot-every`` iterations (the same iterations in both runs), and every snapshot plays the
  same evaluation seeds. Per seed, the chaos run's mean over its snapshots minus the undisturbed
  run's is a paired difference; their mean must not fall below ``-2 sigma``, where ``sigma**2`` is
  the paired differences' squared standard error plus the training noise measured on the
  undisturbed run itself: the variance of its snapshots' mean scores, times ``2 / snapshots`` (a
  difference of two such averages). A final score read at one iteration swings by ~20 % between
  evaluations of the same run (docs/clusters.md), which a bar of the evaluation noise alone
  ignored. A gap or sigma that is not a finite number (a NaN or infinite score) fails too.

    .venv/bin/python scripts/chaos.py --server target/release/dinerdash-server --duration 180 \\
        --undisturbed

The servers and the monkey live in a child process started before JAX: forking a process while
JAX's threads run is unsafe, and the monkey starts servers again and again.
"""

from __future__ import annotations

import argparse
import math
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
#: Seconds a restarted or drained server may take to exit before it is killed: past any
#: ``--drain-timeout`` the runs use.
EXIT_TIMEOUT = 120.0


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
            log = MonkeyLog()
            thread = None
            if monkey:
                thread = threading.Thread(
                    target=_guarded,
                    args=(_monkey, cluster, proxies, random.Random(seed), stop, log),
                )
                thread.start()
            assert pipe.recv() == "stop"
            log.stopped = time.monotonic()
            stop.set()
            if thread is not None:
                thread.join()
            for i, proxy in enumerate(proxies):  # everything up for the evaluation
                proxy.heal()
                cluster.resume(i)
                if not cluster.is_running(i):
                    cluster.restart(i)
            pipe.send((log, cluster.addresses))
            assert pipe.recv() == "close"
        finally:
            for proxy in proxies:
                proxy.close()


@dataclass
class Fault:
    """One fault the monkey made; times are ``time.monotonic()`` (one clock for every process
    of the machine, so the trainer's cut episodes can be set beside them)."""

    began: float
    kind: str
    server: int
    #: When it was over (the server back, the network healed); ``None``: it never was.
    ended: float | None = None


@dataclass
class MonkeyLog:
    """What the fault thread did, sent to the trainer's process at the end."""

    faults: list[Fault] = field(default_factory=list)
    #: When the next fault was due, drawn after the last one ended (``None`` before the first).
    next_due: float | None = None
    #: When the trainer said stop.
    stopped: float | None = None
    #: The exception that ended the fault thread, if one did.
    error: str | None = None


def _guarded(monkey: Any, *args: Any) -> None:
    """Runs the fault thread; an exception that ends it is logged for the judge, never lost."""
    log: MonkeyLog = args[-1]
    try:
        monkey(*args)
    except BaseException as e:  # noqa: BLE001  (reported: the judge fails the run)
        log.error = f"{type(e).__name__}: {e}"
        print(f"[chaos] the fault thread died: {log.error}", flush=True)


def _monkey(
    cluster: Any,
    proxies: list,
    rng: random.Random,
    stop: threading.Event,
    log: MonkeyLog,
):
    began = time.monotonic()
    while True:
        wait = rng.uniform(10.0, 20.0)
        log.next_due = time.monotonic() + wait
        if stop.wait(wait):
            return
        fault, i = rng.choice(FAULTS), rng.randrange(len(proxies))
        recover = rng.uniform(2.0, 8.0)
        record = Fault(time.monotonic(), fault, i)
        log.faults.append(record)
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
        record.ended = time.monotonic()


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
    #: When episodes were cut: ``(time.monotonic(), how many)``.
    cuts: list[tuple[float, int]] = field(default_factory=list)
    failovers: int | None = None
    rejoins: int | None = None
    moves: int | None = None
    #: The evaluation: one row per snapshot (its iteration in ``snapshot_iterations``), one
    #: column per evaluation seed.
    scores: Any = None
    snapshot_iterations: list[int] = field(default_factory=list)


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
                cut = int((info["reconnected"] & info["_reconnected"]).sum())
                if cut:
                    tally.cut += cut
                    tally.cuts.append((time.monotonic(), cut))
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
    the trainer and its policy at the last ``args.snapshots`` multiples of
    ``args.snapshot_every`` iterations (``{iteration: model}``; models are immutable)."""
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
    snapshots: dict[int, Any] = {}

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
            if trainer.iteration % args.snapshot_every == 0:
                snapshots[trainer.iteration] = trainer.model
                for old in sorted(snapshots)[: -args.snapshots]:
                    del snapshots[old]
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
    if not snapshots:  # a run shorter than one snapshot's spacing: its final policy
        snapshots[trainer.iteration] = trainer.model
    return trainer, snapshots


def evaluate(
    trainer: Any, snapshots: dict[int, Any], address: str, args: argparse.Namespace
) -> tuple[Any, list[int]]:
    """Each snapshot's greedy scores on the fixed seeds ``eval_seed`` .. + ``eval_episodes``:
    (snapshots x seeds) and the snapshots' iterations."""
    import numpy as np
    from dinerdash_agents.checkpoint import Policy
    from dinerdash_agents.evaluate import evaluate_policy

    rows = []
    for iteration in sorted(snapshots):
        policy = Policy(snapshots[iteration], {"algorithm": "ppo-masked"})
        scores, _ = evaluate_policy(
            policy.act,
            args.eval_episodes,
            seed=args.eval_seed,
            address=address,
            num_envs=min(64, args.eval_episodes),
            max_steps=trainer.config.max_episode_steps,
        )
        rows.append(np.asarray(scores, dtype=np.float64))
    return np.stack(rows), sorted(snapshots)


def run(
    args: argparse.Namespace, monkey: bool, iterations: int | None = None
) -> tuple[Tally, MonkeyLog]:
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
    tally, log = Tally(), MonkeyLog()
    try:
        proxies = parent.recv()
        parent.send("go")
        try:
            if iterations is None:
                trainer, snapshots = train(proxies, args, tally, duration=args.duration)
            else:
                trainer, snapshots = train(proxies, args, tally, iterations=iterations)
        finally:
            parent.send("stop")
            log, servers = parent.recv()
        tally.scores, tally.snapshot_iterations = evaluate(
            trainer, snapshots, servers[0], args
        )
        parent.send("close")
    finally:
        process.join(timeout=60)
        if process.is_alive():
            process.terminate()
            process.join()
    return tally, log


def _supports_drain(binary: str) -> bool:
    """Whether the server has ``--drain-timeout`` (issue 26's draining)."""
    shown = subprocess.run(
        [binary, "--help"], check=False, capture_output=True, text=True, timeout=30
    )
    return "--drain-timeout" in shown.stdout


#: Faults whose outages may cut episodes: a crash, a hung process, a dead network. A drain or a
#: restart is planned: its sessions move whole, by Snapshot and Restore.
CRASHES = ("kill", "hang", "blackhole")
#: Seconds of slack in the fault thread's own timing (a wake-up, a log line).
SLACK = 1.0


def report(name: str, tally: Tally, log: MonkeyLog | None) -> None:
    import numpy as np

    scores = np.asarray(tally.scores, dtype=np.float64)
    final = scores[-1]
    sem = final.std(ddof=1) / np.sqrt(len(final)) if len(final) > 1 else float("nan")

    def shown(value: int | None) -> str:
        return "n/a (this client has no such counter)" if value is None else f"{value}"

    print(f"\n== {name} ==")
    print(
        f"  trained           {tally.iterations} iterations, {tally.steps:,} env steps, "
        f"{tally.seconds:.0f} s ({tally.steps / max(tally.seconds, 1e-9):,.0f} steps/s)"
    )
    if log is not None:
        faults = log.faults
        kinds = {k: sum(1 for f in faults if f.kind == k) for k in FAULTS}
        print(
            f"  faults            {len(faults)}: "
            + ", ".join(f"{k} {n}" for k, n in kinds.items())
            + (f"; the fault thread died: {log.error}" if log.error else "")
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
        f"  final score       {final.mean():,.1f} ± {sem:,.1f} (mean ± s.e., sd "
        f"{final.std(ddof=1):,.1f}) over {len(final)} evaluation episodes"
    )
    print(
        "  snapshots         "
        + ", ".join(
            f"{i}: {row.mean():,.0f}"
            for i, row in zip(tally.snapshot_iterations, scores)
        )
    )


def score_gap(chaos: Any, calm: Any) -> tuple[float, float]:
    """The chaos run's score minus the undisturbed run's, and its noise ``sigma``.

    ``chaos`` and ``calm`` are (snapshots x seeds) scores of the same snapshot iterations on the
    same seeds. The gap is the mean over seeds of the paired per-seed difference of the two runs'
    snapshot averages. ``sigma**2`` is that mean's squared standard error plus the training
    noise measured on the undisturbed run: the variance of its snapshots' mean scores, times
    ``2 / snapshots`` (the variance of a difference of two such averages); with one snapshot
    there is no training noise to measure and only the evaluation's counts."""
    import numpy as np

    chaos, calm = np.asarray(chaos, np.float64), np.asarray(calm, np.float64)
    if chaos.shape != calm.shape:
        raise ValueError(
            f"the runs' scores differ in shape: {chaos.shape} and {calm.shape}"
        )
    snapshots, seeds = calm.shape
    paired = chaos.mean(axis=0) - calm.mean(axis=0)
    eval_var = paired.var(ddof=1) / seeds if seeds > 1 else 0.0
    train_var = (
        calm.mean(axis=1).var(ddof=1) * 2.0 / snapshots if snapshots > 1 else 0.0
    )
    return float(paired.mean()), float(np.sqrt(eval_var + train_var))


def judge(chaos: Tally, log: MonkeyLog, calm: Tally | None) -> list[str]:
    """Why the chaos run fails (empty: it passes). See the module's doc for each rule."""
    failures = []
    if log.error is not None:
        failures.append(f"the fault thread died: {log.error}")
    elif log.stopped is not None:
        if log.next_due is None:
            failures.append("the fault thread never ran")
        elif log.next_due < log.stopped - SLACK and not any(
            f.began >= log.next_due - SLACK for f in log.faults
        ):
            failures.append(
                f"fewer faults than scheduled: one due {log.stopped - log.next_due:.1f} s "
                "before the stop never began"
            )
    for f in log.faults:
        if f.ended is None:
            failures.append(f"{f.kind} of server {f.server} began and never ended")
    for when, count in chaos.cuts:
        under_way = [f for f in log.faults if f.began <= when]
        if not under_way:
            failures.append(f"{count} episodes cut with no fault begun")
        elif under_way[-1].kind not in CRASHES:
            f = under_way[-1]
            failures.append(
                f"a {f.kind} of server {f.server} cut {count} episodes "
                f"({when - f.began:.1f} s after it began): planned stops must not cut episodes"
            )
    if chaos.exceptions:
        failures.append(f"the chaos run raised {len(chaos.exceptions)} exceptions")
    if calm is not None:
        if calm.exceptions:
            failures.append(
                f"the undisturbed run raised {len(calm.exceptions)} exceptions"
            )
        gap, sigma = score_gap(chaos.scores, calm.scores)
        if not (math.isfinite(gap) and math.isfinite(sigma)):
            failures.append(f"the score gap is not a number: {gap} (sigma {sigma})")
        elif gap < -2 * sigma:
            failures.append(
                f"the score fell by {-gap:,.1f}, more than 2 sigma ({2 * sigma:,.1f})"
            )
    return failures


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
        default=60.0,
        help="the servers' --drain-timeout, if they have it: longer than an episode lasts on a "
        "loaded machine, since a drain that ends before an episode does must cut it",
    )
    parser.add_argument("--eval-episodes", type=int, default=64)
    parser.add_argument("--eval-seed", type=int, default=10_000)
    parser.add_argument(
        "--snapshots",
        type=int,
        default=5,
        help="policies kept at the end of each run, each evaluated on the same seeds",
    )
    parser.add_argument(
        "--snapshot-every", type=int, default=10, help="iterations between snapshots"
    )
    parser.add_argument(
        "--undisturbed",
        action="store_true",
        help="also train the same seed, as many iterations, without the monkey",
    )
    args = parser.parse_args(argv)
    if not 0 <= args.drain_timeout < EXIT_TIMEOUT:
        parser.error(f"--drain-timeout must be in [0, {EXIT_TIMEOUT:g}) s")
    if not Path(args.server).is_file():
        parser.error(f"--server {args.server}: no such binary (make build-server)")
    if args.snapshots < 1 or args.snapshot_every < 1:
        parser.error("--snapshots and --snapshot-every must be at least 1")

    chaos, log = run(args, monkey=True)
    report("chaos", chaos, log)
    calm = None
    if args.undisturbed:
        calm, _ = run(args, monkey=False, iterations=chaos.iterations)
        report("undisturbed, same seed and iterations", calm, None)
        gap, sigma = score_gap(chaos.scores, calm.scores)
        print(
            f"\nchaos - undisturbed over {len(calm.snapshot_iterations)} snapshots "
            f"x {args.eval_episodes} seeds: {gap:+,.1f} (2 sigma: {2 * sigma:,.1f})"
        )
    failures = judge(chaos, log, calm)
    for text in failures:
        print(f"FAILED: {text}")
    print(
        f"exceptions: {len(chaos.exceptions)}; " + ("FAILED" if failures else "passed")
    )
    return 1 if failures else 0


if __name__ == "__main__":
    sys.exit(main())

"""``bench-ppo``: PPO's end-to-end training speed (env-steps/s) and where an iteration's time goes.

It trains masked PPO (the committed hyper-parameters), or the recipe's PPO stage (``ppo-kickstart``
with the settings of :data:`~dinerdash_agents.recipe.PPO`'s row, from a DAgger checkpoint:
memory features computed on the client, expert labels asked of the server), as ``train`` does,
on the same vector envs
(:func:`~dinerdash_agents.train_rl.make_envs`), for a few iterations after one that compiles,
and reads :attr:`~dinerdash_agents.ppo.Trainer.timings`: acting (the jitted calls and their
copies), waiting for the environments (the server's step and the client's decoding, minus what
the pipeline hides), the bootstrap values, the rest of the rollout (buffers and episode
bookkeeping) and the update (advantages included). With a local server it also reports the
server's CPU time, read from ``/proc``.
"""

from __future__ import annotations

import dataclasses
import os
import time
from pathlib import Path
from typing import Any

import jax

from . import ppo
from .connect import ConnectOptions, options, served
from .errors import AgentsError
from .train_rl import PIPELINE, RL, RL_ALGORITHMS, make_envs

__all__ = ["bench_ppo"]


def _cpu_seconds(pid: int | None) -> float | None:
    """User + system CPU time of process ``pid`` (Linux), else ``None``."""
    if pid is None:
        return None
    try:
        fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    except OSError:
        return None
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def _config(algorithm: str, init: str | Path | None) -> tuple[ppo.PPOConfig, dict[str, Any]]:
    """The benchmarked run's config and its environments' game keywords."""
    if init is None:
        return ppo.PPOConfig(masked=RL_ALGORITHMS[algorithm]), {}
    from .kickstart import KickstartConfig
    from .paper import KICKSTART_SETTINGS
    from .recipe import PPO

    config = RL[algorithm].start(KickstartConfig(**KICKSTART_SETTINGS[PPO]), init, None, False)
    return config, RL[algorithm].game(config)


def bench_ppo(
    *,
    algorithm: str = "ppo-masked",
    num_envs: int | None = None,
    iterations: int = 10,
    pipeline: int = PIPELINE,
    address: Any = None,
    connect: ConnectOptions | None = None,
    seed: int = 0,
    init: str | Path | None = None,
    **connection: Any,
) -> dict[str, Any]:
    """Runs ``iterations`` timed PPO iterations (after one untimed) and returns the figures:
    ``env_steps_per_s`` and per iteration ``ms`` by part, CPU seconds (client, server).
    ``init``: ``ppo-kickstart``'s DAgger checkpoint. ``connect``: how to reach the server, with
    ``address`` and the connection keywords put in (none named: ``DINERDASH_ADDRESS``, else a
    local server started here)."""
    if algorithm not in ("ppo", "ppo-masked", "ppo-kickstart"):
        raise AgentsError(f"bench-ppo runs ppo, ppo-masked or ppo-kickstart, not {algorithm!r}")
    if (algorithm == "ppo-kickstart") != (init is not None):
        raise AgentsError("--init DIR (a dagger checkpoint) goes with ppo-kickstart, and only it")
    if iterations < 1:
        raise AgentsError(f"--iterations must be at least 1 (got {iterations})")
    if pipeline < 1:
        raise AgentsError(f"--pipeline must be at least 1 (got {pipeline})")
    connect = options(connect, "bench_ppo", address, **connection)
    # A local server, if any, starts before any JAX work.
    with served(connect) as (connect, server):
        config, game = _config(algorithm, init)
        if num_envs is not None:  # as train: the rollout and minibatches adapted
            config = config.for_num_envs(num_envs)
        envs = make_envs(config, connect, pipeline, **game)
        try:
            high = envs[0].single_observation_space.high
            config = dataclasses.replace(config, observation_high=tuple(high.tolist()))
            per_iteration = config.num_envs * config.num_steps
            trainer = RL[algorithm].trainer(
                config, (iterations + 1) * per_iteration, seed, None, False
            )
            trainer.attach(envs)
            trainer.step()  # compiles
            trainer.timings = dict.fromkeys(ppo.TIMED, 0.0)
            server_pid = server.pid if server is not None else None
            server_cpu, cpu = _cpu_seconds(server_pid), time.process_time()
            began = time.perf_counter()
            walls = []
            for _ in range(iterations):
                trainer.step()
                walls.append(time.perf_counter() - began - sum(walls))
            wall = time.perf_counter() - began
            cpu = time.process_time() - cpu
            server_after = _cpu_seconds(server_pid)
        finally:
            for e in envs:
                e.close()
    t = {k: 1000 * v / iterations for k, v in trainer.timings.items()}
    ms = {
        "act": t["act"],
        "env": t["env"],
        "bootstrap": t["bootstrap"],
        "rollout_other": t["collect"] - t["act"] - t["env"] - t["bootstrap"],
        "update": t["update"],
        "other": 1000 * wall / iterations - t["collect"] - t["update"],
    }
    return {
        "algorithm": algorithm,
        "num_envs": config.num_envs,
        "pipeline": len(envs),
        "iterations": iterations,
        "samples_per_iteration": per_iteration,
        "num_steps": config.num_steps,
        "update_epochs": config.update_epochs,
        "minibatches": config.num_minibatches,
        "device": str(jax.devices()[0].platform),
        "seconds": wall,
        "env_steps_per_s": iterations * per_iteration / wall,
        # The fastest and the median iteration: on a shared machine the fastest is the one
        # least disturbed by other work.
        "env_steps_per_s_best_iteration": per_iteration / min(walls),
        "env_steps_per_s_median_iteration": per_iteration / sorted(walls)[len(walls) // 2],
        "ms_per_iteration": ms,
        "client_cpu_s": cpu,
        "server_cpu_s": None if server_cpu is None else server_after - server_cpu,
    }


def print_bench(r: dict[str, Any]) -> None:
    n, wall, iters = r["num_envs"], r["seconds"], r["iterations"]
    print(
        f"{r['algorithm']}: {n} environments in {r['pipeline']} vector env(s), "
        f"{iters} iterations of {r['samples_per_iteration']} steps in {wall:.2f} s: "
        f"{r['env_steps_per_s']:,.0f} env-steps/s end to end (iterations: best "
        f"{r['env_steps_per_s_best_iteration']:,.0f}/s, median "
        f"{r['env_steps_per_s_median_iteration']:,.0f}/s)"
    )
    total = 1000 * wall / iters
    labels = {
        "act": "act (jitted policy + value, copies)",
        "env": "env (waiting for the server's step + client decoding)",
        "bootstrap": "bootstrap values (truncations, last step)",
        "rollout_other": "rollout bookkeeping (buffers, episodes)",
        "update": f"update (GAE + {r['update_epochs']} epochs x {r['minibatches']} minibatches)",
        "other": "other",
    }
    print(f"  per iteration {total:8.1f} ms")
    for key, label in labels.items():
        v = r["ms_per_iteration"][key]
        print(f"  {label:56s} {v:8.1f} ms  {100 * v / total:5.1f} %")
    line = f"  CPU: client {r['client_cpu_s'] / wall:.2f} cores"
    if r["server_cpu_s"] is not None:
        line += f", server {r['server_cpu_s'] / wall:.2f} cores"
    print(line + f" (over {os.cpu_count()} cores, wall {wall:.2f} s)")

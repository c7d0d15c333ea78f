"""RLlib PPO's env-steps/s on one DinerDash server: our entry point (one batched session per
EnvRunner) against RLlib's default vectorization (one ``gymnasium.make`` env, one session and one
round trip per sub-environment), and the agents' JAX PPO on the same server. A benchmark, not a
test; needs the ``dinerdash[ray]`` extra and ``dinerdash-agents``::

    .venv/bin/python scripts/bench_rllib.py                     # starts a local server
    .venv/bin/python scripts/bench_rllib.py --address host:port --env-runners 4

For each RLlib mode, :func:`dinerdash.ray.masked_ppo` builds the same PPO (only
``gym_env_vectorize_mode`` differs), one ``train()`` warms up, then it measures

- sampling: every EnvRunner's ``sample()`` of ``--envs x 32`` steps at once, with the masked
  module's exploration (what RLlib spends per step apart from learning);
- training: ``train()`` iterations, learning included (env steps sampled / wall time).

The JAX PPO (``python -m dinerdash_agents train ppo-masked``) runs ``--jax-steps`` steps with
``--env-runners x --envs`` environments in one process; its rate is the median of its
``curve.csv`` (``env_steps_per_s`` per iteration, learning included; the first iteration,
which compiles, is left out).
"""

from __future__ import annotations

import argparse
import csv
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import gymnasium as gym


def _rllib(
    address: str, mode: gym.VectorizeMode, args: argparse.Namespace
) -> dict[str, float]:
    from dinerdash.ray import masked_ppo

    config = masked_ppo([address], args.env_runners, args.envs).env_runners(
        gym_env_vectorize_mode=mode
    )
    algo = config.build_algo()
    try:
        algo.train()  # warm-up: the first sample and the learner's first update
        per_runner = args.envs * 32
        began, steps = time.perf_counter(), 0
        for _ in range(args.iterations):
            counts = algo.env_runner_group.foreach_env_runner(
                lambda r, n=per_runner: sum(len(e) for e in r.sample(num_timesteps=n)),
                local_env_runner=False,
            )
            steps += sum(counts)
        sampling = steps / (time.perf_counter() - began)
        before = algo.train()["env_runners"]["num_env_steps_sampled_lifetime"]
        began = time.perf_counter()
        for _ in range(args.iterations):
            after = algo.train()["env_runners"]["num_env_steps_sampled_lifetime"]
        training = (after - before) / (time.perf_counter() - began)
    finally:
        algo.stop()
    return {"sampling": sampling, "training": training}


def _jax(address: str, args: argparse.Namespace) -> float:
    with tempfile.TemporaryDirectory() as tmp:
        out = Path(tmp) / "ppo-masked"
        cmd = [
            sys.executable,
            "-m",
            "dinerdash_agents",
            "train",
            "ppo-masked",
            "--steps",
            str(args.jax_steps),
            "--num-envs",
            str(args.env_runners * args.envs),
            "--out",
            str(out),
            "--address",
            address,
        ]
        subprocess.run(cmd, check=True, stdout=subprocess.DEVNULL)
        with open(out / "curve.csv") as f:
            rates = [float(row["env_steps_per_s"]) for row in csv.DictReader(f)]
    return statistics.median(rates[1:] or rates)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument(
        "--address", help="a running server (default: start a local one)"
    )
    parser.add_argument("--env-runners", type=int, default=2)
    parser.add_argument(
        "--envs", type=int, default=64, help="environments per EnvRunner"
    )
    parser.add_argument("--iterations", type=int, default=3, help="measured iterations")
    parser.add_argument(
        "--jax-steps", type=int, default=200_000, help="0 skips the JAX PPO"
    )
    args = parser.parse_args(argv)

    import ray
    from dinerdash import LocalServer

    server = None if args.address else LocalServer()
    address = args.address or server.address
    try:
        ray.init(
            address="local",  # a Ray of its own, even beside a running cluster
            num_cpus=max(args.env_runners, os.cpu_count() or 1),
            include_dashboard=False,
        )
        rows = []
        for name, mode in (
            (
                "RLlib PPO, dinerdash.ray entry point (1 session per EnvRunner)",
                "vector",
            ),
            ("RLlib PPO, RLlib default vectorization (1 env per sub-env)", "sync"),
        ):
            vmode = (
                gym.VectorizeMode.VECTOR_ENTRY_POINT
                if mode == "vector"
                else gym.VectorizeMode.SYNC
            )
            r = _rllib(address, vmode, args)
            rows.append((name, f"{r['sampling']:,.0f}", f"{r['training']:,.0f}"))
            print(f"{name}: sampling {rows[-1][1]}, training {rows[-1][2]}", flush=True)
        ray.shutdown()
        if args.jax_steps:
            rate = _jax(address, args)
            rows.append(
                ("JAX PPO (dinerdash_agents train ppo-masked)", "-", f"{rate:,.0f}")
            )
            print(f"{rows[-1][0]}: training {rows[-1][2]}", flush=True)
    finally:
        if server is not None:
            server.stop()
    envs = args.env_runners * args.envs
    print(
        f"\n{args.env_runners} EnvRunners x {args.envs} environments ({envs} in all), one "
        f"server, {os.cpu_count()} CPUs\n"
    )
    print("| trainer | env-steps/s sampling | env-steps/s training |")
    print("| --- | ---: | ---: |")
    for row in rows:
        print(f"| {row[0]} | {row[1]} | {row[2]} |")
    return 0


if __name__ == "__main__":
    sys.exit(main())

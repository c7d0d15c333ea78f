"""Example trainer for docker/compose.yaml.

Spreads one Gymnasium vector env over every server named in ``DINERDASH_ADDRESS`` (comma
separated, or a DNS name that resolves to several replicas), plays random legal actions, and
prints episode returns and throughput. Replace the policy with your learner.
"""

import argparse
import os
import time

import dinerdash  # noqa: F401  (registers DinerDash-v0)
import gymnasium as gym
import numpy as np


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--num-envs", type=int, default=96)
    parser.add_argument("--steps", type=int, default=2000)
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()

    addresses = [a.strip() for a in os.environ["DINERDASH_ADDRESS"].split(",") if a.strip()]
    envs = gym.make_vec("dinerdash:DinerDash-v0", num_envs=args.num_envs, address=addresses)
    servers = envs.addresses  # a DNS name with several addresses is several servers
    print(f"{args.num_envs} environments over {', '.join(servers)}", flush=True)
    rng = np.random.default_rng(args.seed)
    _, info = envs.reset(seed=args.seed)
    returns = np.zeros(args.num_envs)
    finished = []
    start = time.perf_counter()
    for _ in range(args.steps):
        # A random legal action per environment: the largest random number among legal actions.
        actions = (rng.random(info["action_mask"].shape) * info["action_mask"]).argmax(axis=1)
        _, reward, terminated, truncated, info = envs.step(actions)
        returns += reward
        done = terminated | truncated
        finished.extend(returns[done].tolist())
        returns[done] = 0
    elapsed = time.perf_counter() - start
    envs.close()
    print(f"{args.steps * args.num_envs / elapsed:,.0f} env-steps/s over {len(servers)} servers")
    if finished:
        print(f"{len(finished)} episodes, mean return {np.mean(finished):.1f}")


if __name__ == "__main__":
    main()

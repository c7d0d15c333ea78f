"""The masked-random baseline: every environment plays a uniformly random legal action (one of
those ``info["action_mask"]`` allows) until its first episode ends; prints the mean and standard
deviation of the scores. Uniform random play over all 57 actions scores about -1,300, since most
actions are illegal in most states and do nothing::

    .venv/bin/python scripts/masked_random.py --seed 0      # seeds 0..99; starts a local server
    .venv/bin/python scripts/masked_random.py --seed 1000 --address host:port
"""

from __future__ import annotations

import argparse

import dinerdash
import numpy as np


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--seed", type=int, default=0, help="first seed (default: 0)")
    parser.add_argument(
        "--episodes", type=int, default=100, help="one per seed (default: 100)"
    )
    parser.add_argument(
        "--rng", type=int, default=0, help="the actions' generator (default: 0)"
    )
    parser.add_argument(
        "--address", help="a running server (default: start a local one)"
    )
    args = parser.parse_args()
    rng = np.random.default_rng(args.rng)
    envs = dinerdash.DinerDashVectorEnv(args.episodes, args.address)
    try:
        _, info = envs.reset(seed=args.seed)
        over = np.zeros(args.episodes, np.bool_)
        scores = np.zeros(args.episodes)
        while not over.all():
            actions = np.array(
                [rng.choice(np.flatnonzero(m)) for m in info["action_mask"]]
            )
            _, rewards, terminated, truncated, info = envs.step(actions)
            scores += np.where(
                over, 0.0, rewards
            )  # an ended environment's next episode: ignored
            over |= terminated | truncated
    finally:
        envs.close()
    last = args.seed + args.episodes - 1
    print(
        f"masked random, seeds {args.seed}..{last}: {scores.mean():,.1f} ± {scores.std(ddof=1):,.1f}"
    )


if __name__ == "__main__":
    main()

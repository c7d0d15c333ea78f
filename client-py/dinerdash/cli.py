"""``python -m dinerdash``: evaluate a policy, collect expert demonstrations, measure speed,
watch a server's sessions in a browser.

::

    python -m dinerdash evaluate --policy expert --episodes 100   # or --policy planner
    python -m dinerdash collect --episodes 274 --out demos/       # --policy planner: its demos
    python -m dinerdash bench
    python -m dinerdash watch --address 127.0.0.1:50051           # the URL of its web pages

Every command takes ``--address host:port`` (several separated by commas); without it (and
without ``DINERDASH_ADDRESS``) a local ``dinerdash-server`` is started and stopped. ``--tls`` (the
system's roots) or ``--tls-ca PATH`` (``DINERDASH_TLS_CA``) connect to a server that serves TLS;
``--timeout`` (``DINERDASH_TIMEOUT``) is every call's deadline in seconds.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import sys
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any, TextIO

import numpy as np

from ._session import EXPERTS

__all__ = [
    "Progress",
    "evaluate_through_env",
    "main",
    "play_seeded",
    "print_evaluation",
    "run_command",
]


class Progress:
    """A dependency-free progress bar on stderr: redrawn in place on a terminal, a line every
    10 % otherwise (CI logs)."""

    def __init__(
        self, total: int, desc: str, stream: TextIO | None = None, width: int = 30
    ) -> None:
        self.total = max(int(total), 1)
        self.desc = desc
        self.stream = stream if stream is not None else sys.stderr
        self.width = width
        self.done = 0
        self.start = time.monotonic()
        self._tty = hasattr(self.stream, "isatty") and self.stream.isatty()
        self._last_draw = 0.0
        self._last_decile = -1

    def update(self, n: int = 1) -> None:
        self.done = min(self.done + n, self.total)
        now = time.monotonic()
        if self._tty:
            if now - self._last_draw >= 0.1 or self.done == self.total:
                self._last_draw = now
                self._draw(now, end="\r")
        else:
            decile = self.done * 10 // self.total
            if decile != self._last_decile:
                self._last_decile = decile
                self._draw(now, end="\n")

    def _draw(self, now: float, end: str) -> None:
        filled = self.width * self.done // self.total
        rate = self.done / max(now - self.start, 1e-9)
        bar = "#" * filled + "." * (self.width - filled)
        self.stream.write(f"{self.desc} [{bar}] {self.done}/{self.total} {rate:,.1f}/s{end}")
        self.stream.flush()

    def close(self) -> None:
        if self._tty:
            self.stream.write("\n")
            self.stream.flush()


def _stats(values: Sequence[float]) -> tuple[float, float, float]:
    """Mean, population sd (the simulator's ``±``) and sample sd."""
    a = np.asarray(values, dtype=np.float64)
    if a.size == 0:
        return math.nan, math.nan, math.nan
    sample = float(a.std(ddof=1)) if a.size > 1 else 0.0
    return float(a.mean()), float(a.std()), sample


def evaluate_through_env(
    policy: str,
    episodes: int,
    *,
    seed: int = 0,
    address: str | None = None,
    num_envs: int = 64,
    max_steps: int = 100_000,
    progress: Progress | None = None,
    **connection: Any,
) -> tuple[np.ndarray, np.ndarray]:
    """Plays ``policy`` through the client's vector env, episode ``i`` reset with ``seed + i``;
    returns the final scores and the lengths. The expert's actions are ``info["expert_action"]``;
    the random policy draws uniformly from 0..56 on the client. ``connection``: ``timeout``,
    ``tls``, ``tls_ca`` of the vector env."""
    from .vector import DinerDashVectorEnv

    n = max(1, min(num_envs, episodes))
    rng = np.random.default_rng(seed)
    expert = policy in EXPERTS

    def act(obs: np.ndarray, info: dict[str, Any]) -> np.ndarray:
        return info["expert_action"] if expert else rng.integers(0, 57, size=n)

    envs = DinerDashVectorEnv(n, address, expert=policy if expert else False, **connection)
    try:
        return play_seeded(envs, act, episodes, seed=seed, max_steps=max_steps, progress=progress)
    finally:
        envs.close()


def play_seeded(
    envs: Any,
    act: Callable[[np.ndarray, dict[str, Any]], np.ndarray],
    episodes: int,
    *,
    seed: int,
    max_steps: int,
    progress: Progress | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Plays ``act(obs, info)`` on the vector env ``envs`` for ``episodes`` episodes, episode
    ``i`` reset with ``seed + i`` (batches of ``envs.num_envs``), each cut at ``max_steps``;
    returns the final scores and the lengths. Every evaluation (the expert, random play, a
    trained agent's checkpoint) plays through this loop, so the same seeds give the same
    episodes."""
    n = envs.num_envs
    scores = np.zeros(episodes, dtype=np.int64)
    lengths = np.zeros(episodes, dtype=np.int64)
    for first in range(0, episodes, n):
        # Seeds past the last episode only pad the batch; their episodes are ignored.
        seeds = [seed + first + i for i in range(n)]
        want = min(n, episodes - first)
        obs, info = envs.reset(seed=seeds)
        done = np.zeros(n, dtype=np.bool_)
        done[want:] = True
        steps = 0
        while not done.all():
            obs, _, terminated, truncated, info = envs.step(act(obs, info))
            steps += 1
            ended = (terminated | truncated | (steps >= max_steps)) & ~done
            if ended.any():
                idx = np.flatnonzero(ended)
                scores[first + idx] = info["score"][idx]
                lengths[first + idx] = steps
                done |= ended
                if progress is not None:
                    progress.update(len(idx))
    return scores, lengths


def _cmd_evaluate(args: argparse.Namespace) -> int:
    progress = Progress(args.episodes, f"{args.policy}")
    start = time.monotonic()
    if args.via == "rollout":
        from .rollout import rollout

        scores, lengths = [], []
        for ep in rollout(
            args.policy,
            episodes=args.episodes,
            seed=args.seed,
            address=args.address,
            max_steps=args.max_steps,
            **_connection(args),
        ):
            scores.append(ep.score)
            lengths.append(ep.steps)
            progress.update()
        how = "server-side rollout"
    else:
        scores, lengths = evaluate_through_env(
            args.policy,
            args.episodes,
            seed=args.seed,
            address=args.address,
            num_envs=args.num_envs,
            max_steps=args.max_steps,
            progress=progress,
            **_connection(args),
        )
        how = f"the client's vector env ({min(args.num_envs, args.episodes)} environments)"
    progress.close()
    print_evaluation(
        args.policy,
        scores,
        lengths,
        seed=args.seed,
        how=how,
        elapsed=time.monotonic() - start,
        as_json=args.json,
    )
    return 0


def print_evaluation(
    policy: str,
    scores: Sequence[int],
    lengths: Sequence[int],
    *,
    seed: int,
    how: str,
    elapsed: float,
    as_json: bool,
) -> None:
    """What ``evaluate`` prints: the episodes, score and length mean ± sd, the speed, and with
    ``as_json`` a last line of JSON (policy, seed, scores, lengths, mean, sd)."""
    episodes = len(scores)
    mean, sd, sample = _stats(scores)
    lmean, lsd, _ = _stats(lengths)
    total = int(np.sum(lengths))
    print(
        f"policy {policy}: {episodes} episodes (seeds {seed}..={seed + episodes - 1}) through {how}"
    )
    print(f"score  {mean:.1f} ± {sd:.1f} (sample sd {sample:.1f})")
    print(f"length {lmean:.1f} ± {lsd:.1f} steps")
    print(f"{total} steps in {elapsed:.3f} s: {total / max(elapsed, 1e-9):.0f} steps/s")
    if as_json:
        print(
            json.dumps(
                {
                    "policy": policy,
                    "seed": seed,
                    "scores": [int(s) for s in scores],
                    "lengths": [int(x) for x in lengths],
                    "mean": mean,
                    "sd": sd,
                }
            )
        )


def _cmd_collect(args: argparse.Namespace) -> int:
    from .rollout import rollout

    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    progress = Progress(args.episodes, "collect")
    episodes = []
    for ep in rollout(
        args.policy,
        episodes=args.episodes,
        seed=args.seed,
        address=args.address,
        max_steps=args.max_steps,
        action_masks=True,
        **_connection(args),
    ):
        episodes.append(ep)
        progress.update()
    progress.close()
    lengths = np.array([ep.steps for ep in episodes], dtype=np.int64)
    terminations = np.concatenate([_last_flag(ep.steps, ep.terminated) for ep in episodes])
    truncations = np.concatenate([_last_flag(ep.steps, ep.truncated) for ep in episodes])
    path = out / f"dinerdash_{args.policy}.npz"
    np.savez_compressed(
        path,
        observations=np.concatenate([ep.observations[:-1] for ep in episodes]),
        next_observations=np.concatenate([ep.observations[1:] for ep in episodes]),
        actions=np.concatenate([ep.actions for ep in episodes]),
        rewards=np.concatenate([ep.rewards for ep in episodes]),
        terminations=terminations,
        truncations=truncations,
        action_masks=np.concatenate([ep.action_masks[:-1] for ep in episodes]),
        episode_lengths=lengths,
        episode_starts=np.concatenate([[0], np.cumsum(lengths)[:-1]]),
        seeds=np.array([ep.seed for ep in episodes], dtype=np.uint64),
        scores=np.array([ep.score for ep in episodes], dtype=np.int64),
    )
    mean, sd, _ = _stats([ep.score for ep in episodes])
    print(
        f"wrote {path}: {len(episodes)} episodes, {int(lengths.sum())} steps, "
        f"score {mean:.1f} ± {sd:.1f}"
    )
    try:
        dataset_id = args.dataset_id or f"dinerdash/{args.policy}-v0"
        minari_path = _write_minari(episodes, out, dataset_id, args.policy)
    except Exception as e:  # minari is optional: say why its dataset is missing, keep the .npz
        print(f"error: could not write the Minari dataset: {e!r}", file=sys.stderr)
        return 1
    if minari_path is not None:
        print(f"wrote Minari dataset {dataset_id} to {minari_path}")
    else:
        print(
            "minari is not installed: skipped the Minari dataset (pip install 'dinerdash[minari]')"
        )
    return 0


def _last_flag(steps: int, value: bool) -> np.ndarray:
    flags = np.zeros(steps, dtype=np.bool_)
    if steps:
        flags[-1] = value
    return flags


def _write_minari(episodes, out: Path, dataset_id: str, policy: str = "expert") -> Path | None:
    """A Minari dataset of the episodes, when ``minari`` is importable; its files go under
    ``out/minari`` unless ``MINARI_DATASETS_PATH`` says otherwise."""
    try:
        import minari  # noqa: F401
    except ImportError:
        return None
    root = Path(os.environ.setdefault("MINARI_DATASETS_PATH", str((out / "minari").resolve())))
    import gymnasium
    from gymnasium import spaces
    from minari import create_dataset_from_buffers
    from minari.data_collector import EpisodeBuffer

    from ._session import NUM_ACTIONS
    from .env import DinerDashEnv

    buffers = [
        EpisodeBuffer(
            id=i,
            seed=int(ep.seed),
            observations=ep.observations,
            actions=ep.actions,
            rewards=list(ep.rewards),
            terminations=list(_last_flag(ep.steps, ep.terminated)),
            truncations=list(_last_flag(ep.steps, ep.truncated)),
            infos={"action_mask": ep.action_masks},
        )
        for i, ep in enumerate(episodes)
    ]
    # The spaces of docs/rules.md section 6, as the server reports them; no server needed here.
    low = np.array([0, 0, -1] * 6 + [0] * 6 + [0, 0] * 7 + [0, 0], dtype=np.float32)
    high = np.array([6, 6, 4] * 6 + [1] * 6 + [4, 6] * 7 + [18, 18], dtype=np.float32)
    create_dataset_from_buffers(
        dataset_id=dataset_id,
        buffer=buffers,
        env=gymnasium.spec("DinerDash-v0"),  # registered by importing dinerdash
        eval_env=gymnasium.spec("DinerDash-v0"),
        observation_space=spaces.Box(low, high, dtype=np.float32),
        action_space=spaces.Discrete(NUM_ACTIONS),
        algorithm_name=(
            "reference expert (docs/rules.md section 8), server-side rollout"
            if policy == "expert"
            else "look-ahead planner, server-side rollout"
        ),
        author="dinerdash",
        description=f"{len(episodes)} {policy} episodes of {DinerDashEnv.__name__}, ruleset v0",
    )
    return root


def _connection(args: argparse.Namespace) -> dict[str, Any]:
    """The connection keywords of the environments and rollout(), from the command line."""
    return {"timeout": args.timeout, "tls": args.tls, "tls_ca": args.tls_ca}


def _cmd_bench(args: argparse.Namespace) -> int:
    from .bench import run

    run(args, _connection(args))
    return 0


def _cmd_watch(args: argparse.Namespace) -> int:
    from .watch import cmd_watch

    return cmd_watch(args, _connection(args))


def _parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="python -m dinerdash", description=__doc__.splitlines()[0]
    )
    sub = parser.add_subparsers(dest="command", required=True)

    def address(p: argparse.ArgumentParser) -> None:
        p.add_argument(
            "--address",
            help="server host:port, several separated by commas (default: DINERDASH_ADDRESS, "
            "else a local server is started)",
        )
        p.add_argument(
            "--tls", action="store_true", help="connect with TLS, trusting the system's roots"
        )
        p.add_argument(
            "--tls-ca",
            metavar="PATH",
            help="connect with TLS, trusting this PEM CA certificate (default: DINERDASH_TLS_CA)",
        )
        p.add_argument(
            "--timeout",
            type=float,
            help="deadline of every call in seconds (default: DINERDASH_TIMEOUT, else 60)",
        )

    p = sub.add_parser("evaluate", help="mean ± sd score of a policy over seeded episodes")
    p.add_argument("--policy", choices=["expert", "random", "planner"], default="expert")
    p.add_argument("--episodes", type=int, default=100)
    p.add_argument(
        "--seed", type=int, default=0, help="seed of the first episode (episode i: seed + i)"
    )
    p.add_argument(
        "--max-steps", type=int, default=100_000, help="truncate an episode after this many steps"
    )
    p.add_argument(
        "--num-envs", type=int, default=64, help="environments stepped together (--via env)"
    )
    p.add_argument(
        "--via",
        choices=["env", "rollout"],
        default="env",
        help="env: step the client's vector env (the expert's actions come from info); "
        "rollout: let the server play whole episodes",
    )
    p.add_argument("--json", action="store_true", help="also print the per-episode scores as JSON")
    address(p)
    p.set_defaults(func=_cmd_evaluate)

    p = sub.add_parser(
        "collect", help="expert demonstrations (.npz; a Minari dataset when installed)"
    )
    p.add_argument(
        "--policy",
        choices=sorted(EXPERTS),
        default="expert",
        help="whose demonstrations: the reference heuristic or the look-ahead planner",
    )
    p.add_argument("--episodes", type=int, default=274)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--out", required=True, help="output directory")
    p.add_argument("--max-steps", type=int, default=None)
    p.add_argument(
        "--dataset-id", default=None, help="Minari dataset id (default: dinerdash/<policy>-v0)"
    )
    address(p)
    p.set_defaults(func=_cmd_collect)

    p = sub.add_parser(
        "bench", help="steps/s of a single env and of make_vec, beside the machine's floors"
    )
    p.add_argument("--steps", type=int, default=20_000, help="single-env steps (0: skip)")
    p.add_argument("--num-envs", type=int, default=256)
    p.add_argument("--vec-steps", type=int, default=2_000, help="vector steps (0: skip)")
    p.add_argument(
        "--pipeline",
        action="store_true",
        help="also two vector envs of --num-envs stepped with step_async/step_wait",
    )
    p.add_argument(
        "--reference-steps",
        type=int,
        default=100_000,
        help="random steps of the in-process pure-Python reference (0: skip)",
    )
    p.add_argument(
        "--servers", type=int, default=1, help="local servers to start when no address is given"
    )
    p.add_argument("--sb3-envs", type=int, default=8, help="environments of the SB3 comparison")
    p.add_argument(
        "--sb3-steps", type=int, default=2_000, help="steps of the SB3 comparison (0: skip)"
    )
    address(p)
    p.set_defaults(func=_cmd_bench)

    p = sub.add_parser(
        "watch",
        help="the URL of a server's web pages (its live sessions, any environment playing); "
        "opens a browser when there is one",
    )
    p.add_argument("--session", help="one session's ID: the URL of its watch page")
    p.add_argument("--env", type=int, default=0, help="the environment of --session to show")
    p.add_argument("--no-browser", action="store_true", help="only print the URL")
    address(p)
    p.set_defaults(func=_cmd_watch)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    return run_command(_parser().parse_args(argv))


def run_command(args: argparse.Namespace, errors: tuple[type[Exception], ...] = ()) -> int:
    """Runs a parsed command (``args.func(args)``) as every ``python -m`` command of this
    project does: ``--address a,b`` becomes a list; the client's errors, and ``errors``, print
    ``error: ...`` and give exit status 1; Ctrl-C gives 130."""
    if getattr(args, "address", None) and "," in args.address:
        args.address = [a for a in args.address.split(",") if a]
    from .errors import LocalServerError, ServiceError

    try:
        return args.func(args)
    except (ServiceError, LocalServerError, *errors) as e:
        print(f"error: {e}", file=sys.stderr)
        return 1
    except KeyboardInterrupt:
        return 130

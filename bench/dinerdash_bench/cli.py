"""``python -m dinerdash bench``: the client's steps/s, single env and vector env, beside the
machine's floors, the server's own rates and the plain-Python reference, measured in one run.

The ``dinerdash`` command forwards ``bench`` and its arguments here (:func:`main`); what each
line measures: docs/benchmarks.md#the-python-client.
"""

from __future__ import annotations

import argparse
from collections.abc import Callable, Sequence
from typing import Any

from dinerdash.cli import (
    DefaultsHelpFormatter,
    add_connection_arguments,
    connection_keywords,
    run_command,
    summary,
)

__all__ = ["main"]


def _above_zero(kind: type) -> Callable[[str], Any]:
    """An argparse type: ``kind(text)``, refused unless above zero."""

    def convert(text: str) -> Any:
        value = kind(text)
        if not value > 0:
            raise argparse.ArgumentTypeError(f"must be above 0, got {text}")
        return value

    convert.__name__ = kind.__name__  # argparse names it in "invalid int value"
    return convert


def _cmd_bench(args: argparse.Namespace) -> int:
    from .harness import run

    run(
        args.address,
        steps=args.steps,
        num_envs=args.num_envs,
        vec_steps=args.vec_steps,
        pipeline=args.pipeline,
        reference_steps=args.reference_steps,
        servers=args.servers,
        sb3_envs=args.sb3_envs,
        sb3_steps=args.sb3_steps,
        compare_transports=not args.no_transports,
        compare_scaling=not args.no_scaling,
        rounds=args.rounds,
        ceiling_seconds=args.ceiling_seconds,
        **connection_keywords(args),
    )
    return 0


def _parser(prog: str) -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog=prog, description=summary(__doc__), formatter_class=DefaultsHelpFormatter
    )
    p.set_defaults(func=_cmd_bench)
    p.add_argument("--steps", type=int, default=20_000, help="single-env steps (0: skip)")
    p.add_argument("--num-envs", type=int, default=256, help="environments of the vector env")
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
    p.add_argument(
        "--no-transports",
        action="store_true",
        help="skip the table of gRPC and shared memory beside the server's own rates",
    )
    p.add_argument(
        "--no-scaling",
        action="store_true",
        help="skip the table of the server's rates by stepping threads beside this client's",
    )
    p.add_argument(
        "--rounds",
        type=_above_zero(int),
        default=3,
        help="rounds of the transports table, taking turns; each figure is the best",
    )
    p.add_argument(
        "--ceiling-seconds",
        type=_above_zero(float),
        default=1.0,
        help="seconds of each measurement of the server's own rates",
    )
    add_connection_arguments(p)
    return p


def main(argv: Sequence[str] | None = None, prog: str = "python -m dinerdash bench") -> int:
    return run_command(_parser(prog).parse_args(argv))

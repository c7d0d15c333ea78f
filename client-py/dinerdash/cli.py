"""``python -m dinerdash``: evaluate a policy, collect expert demonstrations, measure speed,
watch a server's sessions in a browser.

Every command takes ``--address host:port`` (several separated by commas; default:
``DINERDASH_ADDRESS``, else a local server), ``--tls``, ``--tls-ca`` and ``--timeout``
(docs/client.md#the-expert-the-planner-and-the-command-line). What every ``python -m`` command of
the project shares, the agents' too, is here: :func:`add_connection_arguments`,
:func:`connection_keywords` and :func:`run_command`.
"""

from __future__ import annotations

import argparse
import sys
import time
from collections.abc import Callable, Sequence
from typing import Any

from ._arguments import EXPERTS
from .errors import LocalServerError, ServiceError
from .evaluation import EVALUATION_SEEDS

__all__ = [
    "DefaultsHelpFormatter",
    "add_connection_arguments",
    "connection_keywords",
    "main",
    "run_command",
]


# -- what every command shares --------------------------------------------------------------


def _address(text: str) -> str | list[str]:
    """``--address``: one ``host:port`` as given, several (separated by commas) as a list."""
    if "," not in text:
        return text
    return [a for a in text.split(",") if a]


def summary(doc: str) -> str:
    """A module docstring's first paragraph as one line of ``--help`` text, reST quotes dropped."""
    return " ".join(doc.split("\n\n")[0].split()).replace("``", "")


class DefaultsHelpFormatter(argparse.HelpFormatter):
    """``--help`` with each option's default, "(default: X)", unless its help says it already or
    it has none (``None``, a flag's ``False``)."""

    def _get_help_string(self, action: argparse.Action) -> str | None:
        text = action.help or ""
        none = action.default is None or action.default is False
        none = none or action.default == argparse.SUPPRESS  # --help's
        if "(default" in text or not action.option_strings or none:
            return action.help
        return f"{text} (default: %(default)s)"


def add_connection_arguments(parser: argparse.ArgumentParser) -> None:
    """Adds ``--address``, ``--tls``, ``--tls-ca`` and ``--timeout``; :func:`connection_keywords`
    reads the last three back as the environments' keywords."""
    parser.add_argument(
        "--address",
        type=_address,
        help="server host:port, several separated by commas (default: DINERDASH_ADDRESS, "
        "else a local server is started)",
    )
    parser.add_argument(
        "--tls", action="store_true", help="connect with TLS, trusting the system's roots"
    )
    parser.add_argument(
        "--tls-ca",
        metavar="PATH",
        help="connect with TLS, trusting this PEM CA certificate (default: DINERDASH_TLS_CA)",
    )
    parser.add_argument(
        "--timeout",
        type=float,
        help="deadline of every call in seconds (default: DINERDASH_TIMEOUT, else 60)",
    )


def connection_keywords(args: argparse.Namespace) -> dict[str, Any]:
    """``timeout``, ``tls`` and ``tls_ca`` from the command line, as the environments,
    :func:`~dinerdash.rollout` and :mod:`dinerdash.evaluation` take them (``--address`` is
    ``args.address``)."""
    return {"timeout": args.timeout, "tls": args.tls, "tls_ca": args.tls_ca}


def run_command(args: argparse.Namespace, errors: tuple[type[Exception], ...] = ()) -> int:
    """Runs a parsed command (``args.func(args)``, its exit status): the client's errors, files
    that cannot be read or written (``--tls-ca``, ``--out``), and ``errors`` print ``error: ...``
    and give exit status 1; Ctrl-C gives 130."""
    try:
        return args.func(args)
    except (ServiceError, LocalServerError, OSError, *errors) as e:
        print(f"error: {e}", file=sys.stderr)
        return 1
    except KeyboardInterrupt:
        return 130


# -- python -m dinerdash --------------------------------------------------------------------


def _cmd_evaluate(args: argparse.Namespace) -> int:
    from .evaluation import Progress, evaluate_by_rollout, evaluate_through_env, print_evaluation

    progress = Progress(args.episodes, f"{args.policy}")
    start = time.monotonic()
    common = {
        "seed": args.seed,
        "address": args.address,
        "max_steps": args.max_steps,
        "progress": progress,
        **connection_keywords(args),
    }
    if args.via == "rollout":
        scores, lengths = evaluate_by_rollout(args.policy, args.episodes, **common)
        how = "server-side rollout"
    else:
        scores, lengths = evaluate_through_env(
            args.policy, args.episodes, num_envs=args.num_envs, **common
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


def _cmd_collect(args: argparse.Namespace) -> int:
    """``collect``: the expert's episodes, or (``--from-play``) the recordings of /play games
    replayed; then :func:`_write_collected`."""
    from .evaluation import Progress, collect
    from .play import RecordingError, collect_from_play

    where = {"address": args.address, **connection_keywords(args)}
    progress = Progress(
        len(args.from_play or ()) or args.episodes, "replay" if args.from_play else "collect"
    )
    try:
        if args.from_play:
            collected = collect_from_play(args.from_play, args.out, progress=progress, **where)
        else:
            collected = collect(
                args.out,
                policy=args.policy,
                episodes=args.episodes,
                seed=args.seed,
                max_steps=args.max_steps,
                progress=progress,
                **where,
            )
    except RecordingError as e:
        progress.close()
        print(f"error: {e} (nothing written)", file=sys.stderr)
        return 1
    progress.close()
    unit, dataset_id = ("games", "play") if args.from_play else ("episodes", args.policy)
    return _write_collected(collected, unit, args.dataset_id or f"dinerdash/{dataset_id}-v0")


def _write_collected(collected: Any, unit: str, dataset_id: str) -> int:
    """Says what ``collect`` wrote (the ``.npz``: its ``unit``, steps and score) and writes its
    Minari dataset ``dataset_id`` beside it (``minari`` is optional: a missing one is said)."""
    from .evaluation import write_minari

    scores = collected.scores
    print(
        f"wrote {collected.path}: {len(collected.episodes)} {unit}, {collected.steps} steps, "
        f"score {scores.mean():.1f} ± {scores.std():.1f}"
    )
    try:
        minari_path = write_minari(collected, dataset_id)
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


def _cmd_watch(args: argparse.Namespace) -> int:
    import os

    from .connection import Connection
    from .watch import open_browser, pages_url, watch_url

    # The pages are a running server's: with no address, the default port on this machine.
    address = args.address or os.environ.get("DINERDASH_ADDRESS") or "127.0.0.1:50051"
    if isinstance(address, list):
        address = address[0]
    with Connection(address, **connection_keywords(args)) as conn:
        if args.session:
            url = watch_url(conn, args.session, args.env)
        else:
            url = pages_url(conn)
    print(url, flush=True)
    if not args.no_browser and open_browser(url):
        print("opened in your browser", file=sys.stderr)
    return 0


def _parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="python -m dinerdash", description=summary(__doc__))
    sub = parser.add_subparsers(dest="command", required=True)

    def command(name: str, func: Callable[[argparse.Namespace], int], **kwargs: Any):
        p = sub.add_parser(name, formatter_class=DefaultsHelpFormatter, **kwargs)
        p.set_defaults(func=func)
        return p

    p = command("evaluate", _cmd_evaluate, help="mean ± sd score of a policy over seeded episodes")
    p.add_argument(
        "--policy", choices=["expert", "random", "planner"], default="expert", help="who plays"
    )
    p.add_argument("--episodes", type=int, default=100, help="episodes to play")
    p.add_argument(
        "--seed",
        type=int,
        default=EVALUATION_SEEDS.start,
        help="seed of the first episode (episode i: seed + i); the default is the first of the "
        f"evaluation seeds {EVALUATION_SEEDS.start}..{EVALUATION_SEEDS.stop - 1}, which no agent "
        "trains on",
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

    p = command(
        "collect",
        _cmd_collect,
        help="expert demonstrations (.npz; a Minari dataset when installed)",
    )
    p.add_argument(
        "--policy",
        choices=sorted(EXPERTS),
        default="expert",
        help="whose demonstrations: the reference heuristic or the look-ahead planner",
    )
    p.add_argument("--episodes", type=int, default=274, help="episodes to collect")
    p.add_argument(
        "--seed",
        type=int,
        default=0,
        help="seed of the first episode (episode i: seed + i): training seeds, below the "
        f"evaluation seeds {EVALUATION_SEEDS.start}..{EVALUATION_SEEDS.stop - 1}",
    )
    p.add_argument("--out", required=True, help="output directory")
    p.add_argument(
        "--max-steps", type=int, default=None, help="truncate an episode after this many steps"
    )
    p.add_argument(
        "--dataset-id", default=None, help="Minari dataset id (default: dinerdash/<policy>-v0)"
    )
    p.add_argument(
        "--from-play",
        nargs="+",
        metavar="REC.json",
        help="instead of the expert: replay these recordings of /play games (dinerdash_play.npz, "
        "Minari dinerdash/play-v0); --policy and --episodes are then ignored",
    )

    # main() hands `bench` and what follows to dinerdash-bench; here for the list of commands.
    sub.add_parser(
        "bench",
        add_help=False,
        help="steps/s of a single env and of make_vec, beside the machine's floors "
        "(the dinerdash-bench package)",
    )

    p = command(
        "watch",
        _cmd_watch,
        help="the URL of a server's web pages (its live sessions, any environment playing); "
        "opens a browser when there is one",
        description="Prints the URL of the web pages of the server at --address (default: "
        "DINERDASH_ADDRESS, else 127.0.0.1:50051; it must run with --http-port).",
    )
    p.add_argument("--session", help="one session's ID: the URL of its watch page")
    p.add_argument("--env", type=int, default=0, help="the environment of --session to show")
    p.add_argument("--no-browser", action="store_true", help="only print the URL")
    for p in sub.choices.values():
        add_connection_arguments(p)
    return parser


def _bench(argv: Sequence[str]) -> int:
    """``bench``: dinerdash-bench's command, given every argument after ``bench``."""
    try:
        from dinerdash_bench.cli import main as bench
    except ModuleNotFoundError as e:
        if (e.name or "").partition(".")[0] != "dinerdash_bench":
            raise  # one of the bench's own imports
        print(
            "error: `bench` is the dinerdash-bench package's, which is not installed: "
            "pip install dinerdash-bench (from a clone: pip install -e bench)",
            file=sys.stderr,
        )
        return 1
    return bench(argv)


def main(argv: Sequence[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else list(argv)
    if argv[:1] == ["bench"]:
        return _bench(argv[1:])
    return run_command(_parser().parse_args(argv))

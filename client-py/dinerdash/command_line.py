"""What every ``python -m`` command of the project shares, ``dinerdash``'s and the agents': the
connection arguments and how a parsed command runs.

::

    def play(args: argparse.Namespace) -> int:
        env = DinerDashEnv(args.address, **connection_keywords(args))
        ...
        return 0

    parser = argparse.ArgumentParser()
    add_connection_arguments(parser)  # --address, --tls, --tls-ca, --timeout
    parser.set_defaults(func=play)
    raise SystemExit(run_command(parser.parse_args()))
"""

from __future__ import annotations

import argparse
import sys
from typing import Any

from .errors import LocalServerError, ServiceError

__all__ = ["add_connection_arguments", "connection_keywords", "run_command"]


def _address(text: str) -> str | list[str]:
    """``--address``: one ``host:port`` as given, several (separated by commas) as a list."""
    if "," not in text:
        return text
    return [a for a in text.split(",") if a]


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

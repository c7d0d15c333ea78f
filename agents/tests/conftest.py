"""Fixtures of the agents' tests: a real ``dinerdash-server`` on 127.0.0.1 (port 0, stopped by
the fixture) and a small demonstrations file collected from it."""

from __future__ import annotations

import os
from collections.abc import Iterator
from pathlib import Path

import pytest


@pytest.fixture(scope="session", autouse=True)
def server_address() -> Iterator[str]:
    """Started first (autouse): forking the server after JAX has started its threads is unsafe."""
    from dinerdash.server import LocalServer

    for key in ("DINERDASH_AUTH_TOKEN", "DINERDASH_ADDRESS"):
        os.environ.pop(key, None)
    with LocalServer() as server:
        yield server.address


@pytest.fixture(scope="session")
def expert_demos(server_address: str, tmp_path_factory: pytest.TempPathFactory) -> Path:
    """20 expert episodes (seeds 0..19), as ``python -m dinerdash collect`` writes them."""
    from dinerdash.evaluation import collect

    out = tmp_path_factory.mktemp("demos")
    return collect(out, episodes=20, seed=0, address=server_address).path

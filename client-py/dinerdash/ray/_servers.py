"""``dinerdash-server`` processes placed on a Ray cluster by Ray actors: :func:`start_servers` and
its :class:`ServerPool` (docs/clusters.md#servers-start_servers). Only Ray and
:mod:`dinerdash.server` are imported here, so that the actors start without RLlib and torch.
"""

from __future__ import annotations

import os
import sys
import tempfile
import threading
import uuid
from pathlib import Path
from typing import Any

from ..errors import LocalServerError
from ..server import LocalServer, server_args

try:
    import ray
    from ray.util.scheduling_strategies import NodeAffinitySchedulingStrategy
except ImportError as e:  # pragma: no cover - depends on the installed extras
    raise ImportError(f"dinerdash.ray needs Ray ({e}): pip install 'dinerdash[ray]'") from e

__all__ = ["MAX_RESTARTS", "SERVER_RESOURCE", "ServerPool", "ServerPoolError", "start_servers"]

#: A node started with this custom resource (``ray start --resources='{"dinerdash_server": 1}'``)
#: is a server node: when any node has it, :func:`start_servers` uses only those.
SERVER_RESOURCE = "dinerdash_server"
#: How often Ray restarts a server that died (its actor is restarted, the server with it).
MAX_RESTARTS = 20
#: Seconds a restarted server retries its old port while the killed one lets go of it.
_PORT_RETRY_SECONDS = 15.0


class ServerPoolError(LocalServerError):
    """The servers of a :class:`ServerPool` could not be placed or started."""


class _ServerActor:
    """One ``dinerdash-server`` on this actor's node, on the port kept in a file named by its key
    (so that the actor Ray restarts starts it on the same port). When the server exits without
    :meth:`stop`, the actor exits too, so that Ray restarts both."""

    def __init__(self, key: str, token: str | None, args: list[str]) -> None:
        self._stopping = False
        self._port_file = Path(tempfile.gettempdir()) / "dinerdash-ray" / f"{key}.port"
        port = int(self._port_file.read_text()) if self._port_file.is_file() else 0
        if token is not None:
            # Through the environment, not the command line: ps shows no token.
            os.environ["DINERDASH_AUTH_TOKEN"] = token
        self._server = LocalServer(
            host=ray.util.get_node_ip_address(),
            port=port,
            args=args,
            rebind_timeout=_PORT_RETRY_SECONDS,
        )
        self._port_file.parent.mkdir(parents=True, exist_ok=True)
        self._port_file.write_text(self._server.address.rsplit(":", 1)[1])
        threading.Thread(target=self._watch, name="dinerdash-server-watch", daemon=True).start()

    def _watch(self) -> None:
        process = self._server.process
        process.wait()
        if not self._stopping:
            print(
                f"dinerdash-server at {self._server.address} exited with status "
                f"{process.returncode}; its actor exits so that Ray restarts both",
                file=sys.stderr,
                flush=True,
            )
            os._exit(1)

    def address(self) -> str:
        return self._server.address

    def pid(self) -> int:
        return self._server.pid

    def node_id(self) -> str:
        return ray.get_runtime_context().get_node_id()

    def stop(self) -> None:
        self._stopping = True
        self._server.stop()
        self._port_file.unlink(missing_ok=True)


def _server_nodes() -> list[dict[str, Any]]:
    """The alive nodes that run servers: those with :data:`SERVER_RESOURCE` if any has it,
    else all of them; in a fixed order (address, then node id)."""
    nodes = [n for n in ray.nodes() if n.get("Alive")]
    marked = [n for n in nodes if n.get("Resources", {}).get(SERVER_RESOURCE, 0) > 0]
    chosen = marked or nodes
    return sorted(chosen, key=lambda n: (n["NodeManagerAddress"], n["NodeID"]))


class ServerPool:
    """``dinerdash-server`` processes run by Ray actors, one or more per node.

    Attributes:
        addresses: ``host:port`` of each server (the node's IP, the port the server picked).
        node_ids: the Ray node of each server.
        actors: the actor handles (methods ``address``, ``pid``, ``node_id``, ``stop``).
    """

    def __init__(self, actors: list[Any], addresses: list[str], node_ids: list[str]) -> None:
        self.actors = actors
        self.addresses = addresses
        self.node_ids = node_ids
        self._closed = False

    def pids(self) -> list[int]:
        """The servers' process ids (each on its own node)."""
        return ray.get([a.pid.remote() for a in self.actors])

    def close(self, timeout: float = 30.0) -> None:
        """Stops every server and its actor (no restart); safe to call twice."""
        if self._closed:
            return
        self._closed = True
        pending = [a.stop.remote() for a in self.actors]
        try:
            ray.wait(pending, num_returns=len(pending), timeout=timeout)
        finally:
            for actor in self.actors:
                ray.kill(actor, no_restart=True)

    def __enter__(self) -> ServerPool:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def __len__(self) -> int:
        return len(self.addresses)

    def __repr__(self) -> str:
        state = "closed" if self._closed else "running"
        return f"ServerPool({self.addresses!r}, {state})"


def start_servers(
    per_node: int = 1,
    num_servers: int | None = None,
    token: str | None = None,
    **server_flags: Any,
) -> ServerPool:
    """Starts ``dinerdash-server`` processes on the Ray cluster, each under an actor pinned to its
    node and reserving no CPU, and returns their :class:`ServerPool` once every one listens.

    ``per_node`` servers on each node with :data:`SERVER_RESOURCE` (or, when none has it, on
    every alive node), or ``num_servers`` dealt over them in turn; ``token``: the servers' auth
    token (give the clients the same); ``server_flags``: ``max_sessions=20000`` for
    ``--max-sessions 20000``. :class:`ServerPoolError`: no node, or a server that did not start.
    """
    if not ray.is_initialized():
        ray.init()
    if per_node < 1:
        raise ValueError(f"per_node must be at least 1, got {per_node}")
    chosen = "chosen by the pool (the node's address, a free port, token=)"
    args = server_args(server_flags, dict.fromkeys(("host", "port", "auth_token"), chosen))
    nodes = _server_nodes()
    if not nodes:
        raise ServerPoolError("start_servers(): the Ray cluster has no alive node")
    count = len(nodes) * per_node if num_servers is None else int(num_servers)
    if count < 1:
        raise ValueError(f"num_servers must be at least 1, got {num_servers}")
    remote = ray.remote(_ServerActor).options  # options per actor: its node
    actors = []
    placed = []
    for i in range(count):
        node = nodes[i % len(nodes)]
        actor = remote(
            num_cpus=0,
            max_restarts=MAX_RESTARTS,
            scheduling_strategy=NodeAffinitySchedulingStrategy(node["NodeID"], soft=False),
        ).remote(uuid.uuid4().hex, token, args)
        actors.append(actor)
        placed.append(node["NodeID"])
    try:
        addresses = ray.get([a.address.remote() for a in actors])
    except ray.exceptions.RayActorError as e:
        for actor in actors:
            ray.kill(actor, no_restart=True)
        raise ServerPoolError(f"start_servers(): a server did not start: {e}") from None
    return ServerPool(actors, addresses, placed)

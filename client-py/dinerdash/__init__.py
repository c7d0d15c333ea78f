"""DinerDash Gym: the Diner Dash benchmark as a Gymnasium environment served over gRPC.

::

    import gymnasium
    env = gymnasium.make("dinerdash:DinerDash-v0", address="localhost:50051", expert=True)
    envs = gymnasium.make_vec("dinerdash:DinerDash-v0", num_envs=256, address="localhost:50051")

Layout:
    game          the game's numbers (actions, observation size and bounds), defined once
    connection    ConnectOptions (how to connect, one value for envs, rollout and agents), the
                  channel and the one call wrapper (address rules, deadline, TLS, errors, retries)
    errors        the exception hierarchy (mapped from the server's structured error details)
    _arguments    the envs' Python arguments checked and turned into protocol messages
    _endpoint     Endpoint: the connections to the server(s), or the local server, reconnecting
    _session      the session core: one batched session on one server (create, reset, step,
                  reconnect, its transport and the changes of it), shared by both environments
    _transport    Transport: how a session's Steps travel (gRPC, or shared memory: _shm)
    _shm          the shared-memory channel: doorbell, peer check, the region's views
    _step_thread  the thread that makes a core's Steps for step_async / step_wait
    _batch        Batch: a reply's arrays, whatever transport carried them, decoded once; its
                  operations (slice, join, an episode cut) and the Gymnasium observations
                  and infos made of it
    _failover     moving a lost server's environments to the servers left (failover_after)
    _fleet        Fleet: a vector env's slices (server, session, range of environments), moved
                  between servers by Snapshot and Restore (drains, servers taken in, balance)
    _membership   the liveness watch of calls in flight, and the discovery of servers to take in
    _grpc_settings  gRPC process settings applied before grpc is first imported
    env           DinerDashEnv, the Gymnasium Env
    vector        DinerDashVectorEnv, the VectorEnv (one batched session per server)
    server        LocalServer, the embedded default: a dinerdash-server subprocess
    _version      __version__, and ServerVersionWarning for a server of another major/minor
    render        the rgb_array picture, drawn with numpy
    rollout       rollout(): server-side expert/random/planner episodes, streamed
    evaluation    seeded play, evaluate, collect demonstrations, print results, progress bar
    cli           ``python -m dinerdash`` (evaluate, collect, bench, watch), and what every
                  ``python -m`` command shares (connection arguments, run_command)
    bench/        the bench command (harness) and reference, the plain-Python rules it
                  measures against
    sb3           make_vec_env(): a stable-baselines3 VecEnv over one batched session (extra [sb3])
"""

from __future__ import annotations

import gymnasium

from . import _grpc_settings  # noqa: F401  (first: gRPC settings must precede the first import of grpc)
from ._version import ServerVersionWarning
from ._version import __version__ as __version__
from .connection import Connection, ConnectOptions
from .env import DinerDashEnv, Snapshot
from .errors import (
    EnvClosed,
    EpisodeOver,
    FailedPrecondition,
    InvalidArgument,
    LocalServerError,
    NoServerLeft,
    ResourceExhausted,
    ServerBinaryNotFound,
    ServerDraining,
    ServiceError,
    ServiceInternalError,
    ServiceTimeout,
    ServiceTransportError,
    SessionNotFound,
    TLSMismatch,
    Unauthenticated,
)
from .rollout import Episode, rollout
from .server import LocalServer
from .vector import DinerDashVectorEnv

__all__ = [
    "ConnectOptions",
    "Connection",
    "DinerDashEnv",
    "DinerDashVectorEnv",
    "EnvClosed",
    "Episode",
    "EpisodeOver",
    "FailedPrecondition",
    "InvalidArgument",
    "LocalServer",
    "LocalServerError",
    "NoServerLeft",
    "ResourceExhausted",
    "ServerBinaryNotFound",
    "ServerDraining",
    "ServerVersionWarning",
    "ServiceError",
    "ServiceInternalError",
    "ServiceTimeout",
    "ServiceTransportError",
    "SessionNotFound",
    "Snapshot",
    "TLSMismatch",
    "Unauthenticated",
    "rollout",
]

if "DinerDash-v0" not in gymnasium.registry:
    gymnasium.register(
        id="DinerDash-v0",
        entry_point="dinerdash.env:DinerDashEnv",
        vector_entry_point="dinerdash.vector:DinerDashVectorEnv",
    )

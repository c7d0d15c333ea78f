"""DinerDash Gym: the Diner Dash benchmark as a Gymnasium environment served over gRPC.

::

    import gymnasium
    env = gymnasium.make("dinerdash:DinerDash-v0", address="localhost:50051", expert=True)
    envs = gymnasium.make_vec("dinerdash:DinerDash-v0", num_envs=256, address="localhost:50051")

The modules and what each owns: docs/client.md#the-package.
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

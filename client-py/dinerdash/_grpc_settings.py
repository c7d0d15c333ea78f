"""gRPC process settings, applied before ``grpc`` is first imported (this module is imported
first by the package): the client turns grpcio's EventEngine client off unless the process chose
(``GRPC_EXPERIMENTS``) or ``DINERDASH_GRPC_TUNING=0`` (why: docs/client.md#connecting).
"""

from __future__ import annotations

import os
import sys

if (
    "grpc" not in sys.modules
    and "GRPC_EXPERIMENTS" not in os.environ
    and os.environ.get("DINERDASH_GRPC_TUNING", "1") != "0"
):
    os.environ["GRPC_EXPERIMENTS"] = "-event_engine_client"

"""gRPC process settings, applied before ``grpc`` is first imported (this module is imported
first by the package).

grpcio runs the synchronous client's calls on its EventEngine client by default. Measured on the
project's 2-core machine, one small unary call (a single-environment Step) costs about a quarter
more CPU that way than on gRPC's classic I/O manager, and a Step is nothing but one such call. So,
unless the process already chose (``GRPC_EXPERIMENTS`` set) or already imported ``grpc``, the
client turns that experiment off. ``DINERDASH_GRPC_TUNING=0`` leaves gRPC's defaults alone.
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

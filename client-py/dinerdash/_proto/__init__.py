"""Generated gRPC stubs for ``proto/dinerdash/v1/dinerdash.proto``.

Do not edit the ``dinerdash_pb2*`` files: ``scripts/gen_proto.py`` regenerates them, and a test
fails when they drift from the proto.
"""

from . import dinerdash_pb2 as pb
from . import dinerdash_pb2_grpc as pb_grpc

__all__ = ["pb", "pb_grpc"]

#!/usr/bin/env python3
"""Regenerates the committed gRPC stubs in ``dinerdash/_proto/`` from ``../proto``.

Run from anywhere, with the ``dev`` extra installed (it brings ``grpcio-tools``)::

    python client-py/scripts/gen_proto.py            # rewrite the stubs in place
    python client-py/scripts/gen_proto.py --out DIR  # write them elsewhere (the drift test does)

The stubs are committed so that a plain ``pip install`` needs no code generator; the drift test
``tests/test_proto_drift.py`` regenerates them into a temporary directory and fails if they differ.
"""

from __future__ import annotations

import argparse
import sys
import tempfile
from pathlib import Path

CLIENT_DIR = Path(__file__).resolve().parent.parent
PROTO_ROOT = CLIENT_DIR.parent / "proto"
PROTO_FILE = "dinerdash/v1/dinerdash.proto"
OUT_DIR = CLIENT_DIR / "dinerdash" / "_proto"
# The generated modules, flattened into one package beside a small ``__init__``.
GENERATED = ("dinerdash_pb2.py", "dinerdash_pb2.pyi", "dinerdash_pb2_grpc.py")


def generate(out_dir: Path, proto_root: Path = PROTO_ROOT) -> list[Path]:
    """Compiles the proto into ``out_dir`` and returns the files written."""
    from grpc_tools import protoc  # only needed here, hence the local import

    include = Path(protoc.__file__).parent / "_proto"  # well-known types shipped with grpcio-tools
    with tempfile.TemporaryDirectory() as tmp:
        argv = [
            "grpc_tools.protoc",
            f"-I{proto_root}",
            f"-I{include}",
            f"--python_out={tmp}",
            f"--pyi_out={tmp}",
            f"--grpc_python_out={tmp}",
            str(proto_root / PROTO_FILE),
        ]
        if protoc.main(argv) != 0:
            raise RuntimeError(f"protoc failed on {proto_root / PROTO_FILE}")
        out_dir.mkdir(parents=True, exist_ok=True)
        written = []
        for name in GENERATED:
            text = (Path(tmp) / "dinerdash" / "v1" / name).read_text()
            # protoc writes absolute imports that mirror the proto package; the stubs live in
            # ``dinerdash._proto`` instead, so the grpc module imports its sibling relatively.
            text = text.replace(
                "from dinerdash.v1 import dinerdash_pb2 as dinerdash_dot_v1_dot_dinerdash__pb2",
                "from . import dinerdash_pb2 as dinerdash_dot_v1_dot_dinerdash__pb2",
            )
            (out_dir / name).write_text(text)
            written.append(out_dir / name)
    return written


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, default=OUT_DIR, help="output directory")
    args = parser.parse_args(argv)
    if not (PROTO_ROOT / PROTO_FILE).is_file():
        print(f"error: {PROTO_ROOT / PROTO_FILE} not found", file=sys.stderr)
        return 1
    for path in generate(args.out):
        print(path)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

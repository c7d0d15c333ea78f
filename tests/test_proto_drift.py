"""The committed stubs in client-py/dinerdash/_proto match what the proto generates today."""

from __future__ import annotations

import importlib.util
import re
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parent.parent
CLIENT = REPO / "client-py"
# Lines that name the generator's version rather than the contract: compared only when the
# installed grpcio-tools is the one that generated the committed stubs.
_VERSION_LINES = re.compile(
    r"^(# Protobuf Python Version: .*|GRPC_GENERATED_VERSION = .*|    \d+,)$", re.MULTILINE
)


def _load_gen_proto():
    spec = importlib.util.spec_from_file_location("gen_proto", CLIENT / "scripts" / "gen_proto.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_committed_stubs_match_the_proto(tmp_path: Path) -> None:
    if importlib.util.find_spec("grpc_tools") is None:
        pytest.fail("grpcio-tools is needed to check the stubs: pip install -e 'client-py[dev]'")
    gen = _load_gen_proto()
    gen.generate(tmp_path)
    for name in gen.GENERATED:
        fresh = (tmp_path / name).read_text()
        committed = (gen.OUT_DIR / name).read_text()
        if fresh != committed:
            fresh_n = _VERSION_LINES.sub("<version>", fresh)
            committed_n = _VERSION_LINES.sub("<version>", committed)
            assert fresh_n == committed_n, (
                f"client-py/dinerdash/_proto/{name} is out of date with proto/; run "
                "`python client-py/scripts/gen_proto.py`"
            )


def test_stubs_carry_the_proto_descriptor() -> None:
    """Independent of the generator: every message and RPC of the proto file is in the stubs."""
    from dinerdash._proto import pb

    text = (REPO / "proto" / "dinerdash" / "v1" / "dinerdash.proto").read_text()
    messages = set(re.findall(r"^message (\w+)", text, re.MULTILINE))
    rpcs = set(re.findall(r"^\s*rpc (\w+)\(", text, re.MULTILINE))
    assert messages == set(pb.DESCRIPTOR.message_types_by_name)
    assert rpcs == {m.name for m in pb.DESCRIPTOR.services_by_name["DinerDash"].methods}
    for name in messages:
        body = re.search(rf"^message {name} \{{(\}}|.*?^\}})", text, re.MULTILINE | re.DOTALL)
        field_decl = r"^\s+(?:optional |repeated )?[\w.]+ (\w+) = \d+;"
        declared = set(re.findall(field_decl, body.group(1), re.MULTILINE))
        assert declared == set(pb.DESCRIPTOR.message_types_by_name[name].fields_by_name), name

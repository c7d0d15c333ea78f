"""The Batch's fields are written once on the client (:data:`dinerdash._batch.FIELDS`), and that
one table is what the server sends: every field of ``dinerdash.v1.Batch`` (gRPC), with its
repeated-or-packed form, and the arrays of the shared-memory region in the server's order and
widths (``server/src/shm/layout.rs``), which the client's shared-memory reader follows."""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np
from dinerdash import _batch, _shm, game
from dinerdash._proto import pb
from google.protobuf.descriptor import FieldDescriptor

LAYOUT_RS = Path(__file__).resolve().parent.parent / "server" / "src" / "shm" / "layout.rs"
#: What a Batch says of the whole reply, not per environment.
WHOLE = {"num_envs", "drain_remaining_ms"}


def server_layout() -> list[tuple[str, int]]:
    """``FIELDS`` of layout.rs: each array's name and bytes per environment."""
    text = LAYOUT_RS.read_text()
    table = re.search(r"pub const FIELDS: \[\(&str, usize\); \d+\] = \[(.*?)\];", text, re.S)
    assert table, f"no FIELDS table in {LAYOUT_RS}"
    sizes = {"OBSERVATION_SIZE": game.OBSERVATION_SIZE, "NUM_ACTIONS": game.NUM_ACTIONS}
    rows = re.findall(r'\("(\w+)",\s*(\w+)\)', table.group(1))
    return [(name, int(size) if size.isdigit() else sizes[size]) for name, size in rows]


def test_the_field_table_is_the_protos_batch() -> None:
    fields = {f.name: f for f in pb.Batch.DESCRIPTOR.fields if f.name not in WHOLE}
    assert set(_batch.FIELDS) == set(fields)
    for name, field in fields.items():
        if hasattr(field, "is_repeated"):
            repeated = field.is_repeated
        else:  # protobuf before 6
            repeated = field.label == FieldDescriptor.LABEL_REPEATED
        assert repeated == (name in _batch.REPEATED), name
        if not repeated:
            assert field.type == FieldDescriptor.TYPE_BYTES, name
        else:
            bits = {FieldDescriptor.CPPTYPE_UINT32: 32, FieldDescriptor.CPPTYPE_UINT64: 64}
            assert bits[field.cpp_type] == np.dtype(_batch.FIELDS[name][0]).itemsize * 8, name


def test_the_field_table_is_the_servers_shared_memory_layout() -> None:
    layout = server_layout()
    assert [name for name, _ in layout] == list(_shm.FIELDS) == ["actions", *_batch.FIELDS]
    widths = dict(layout)
    assert widths["actions"] == 4  # int32 actions
    for name, (dtype, width) in _batch.FIELDS.items():
        assert widths[name] == np.dtype(dtype).itemsize * width, name

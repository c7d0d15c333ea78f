"""Every checkpoint committed under docs/results/checkpoints loads, and replays the first
ten evaluation seeds of the results table with the scores ``results.json`` reports for them (the
table's numbers come from these files, played through the same evaluation loop)."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from dinerdash_agents import load
from dinerdash_agents.evaluate import evaluate_policy

RESULTS = Path(__file__).resolve().parents[2] / "docs" / "results"
#: Seeds replayed per checkpoint: the table's first ten (1000..1009), played as one batch.
REPLAYED = 10


def _checkpoints() -> list[tuple[str, Path, list[int]]]:
    """(row name, checkpoint directory, its scores on 1000.. in results.json) of every committed
    checkpoint that the table holds a row for (seed k > 0 of a row: its ``runs[k]``)."""
    results = json.loads((RESULTS / "results.json").read_text())
    rows = {row["name"]: row for row in results["agents"]}
    out = []
    for directory in sorted((RESULTS / "checkpoints").iterdir()):
        name, _, k = directory.name.partition("-seed")
        row = rows.get(name) or rows.get(directory.name)
        if row is None or not (directory / "checkpoint.json").is_file():
            continue
        scores = row["runs"][int(k)] if k else row["scores"]
        out.append((directory.name, directory, scores))
    return out


def test_every_committed_checkpoint_has_a_row() -> None:
    names = {name for name, _, _ in _checkpoints()}
    on_disk = {p.name for p in (RESULTS / "checkpoints").iterdir() if p.is_dir()}
    assert names == on_disk


@pytest.mark.parametrize(
    ("name", "directory", "scores"), _checkpoints(), ids=[c[0] for c in _checkpoints()]
)
def test_a_committed_checkpoint_replays_its_table_scores(
    name: str, directory: Path, scores: list[int], server_address: str
) -> None:
    policy = load(directory)
    played, _ = evaluate_policy(
        policy.act,
        REPLAYED,
        seed=1000,
        address=server_address,
        num_envs=REPLAYED,
        use_mask=not name.endswith("(no mask)"),
    )
    assert played.tolist() == scores[:REPLAYED], name

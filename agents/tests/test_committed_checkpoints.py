"""Every committed checkpoint (``docs/results/checkpoints``) loads and plays, greedily, the first
evaluation seeds of the results table exactly as ``docs/results/results.json`` reports them:
its per-episode final scores on seeds 1000, 1001, 1002, with and without the action mask as the
table's rows say. A change to the game, the client, an agent's network or the checkpoint loader
that alters what a committed agent does fails here."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from dinerdash_agents import load
from dinerdash_agents.evaluate import evaluate_policy

RESULTS = Path(__file__).resolve().parents[2] / "docs" / "results"
CHECKPOINTS = RESULTS / "checkpoints"
#: Evaluation episodes replayed per row: seeds 1000.. (the table's first ones).
EPISODES = 3
NO_MASK = " (no mask)"


def _results() -> dict:
    return json.loads((RESULTS / "results.json").read_text())


ROWS = _results()["agents"]


def test_every_committed_checkpoint_has_rows_and_every_row_a_checkpoint() -> None:
    committed = {p.parent.name for p in CHECKPOINTS.glob("*/checkpoint.json")}
    named = {row["name"].removesuffix(NO_MASK) for row in ROWS}
    assert len(committed) >= 15, sorted(committed)
    assert committed == named, (sorted(committed - named), sorted(named - committed))
    assert _results()["evaluation"]["seeds"] == "1000..1099"


@pytest.mark.parametrize("row", ROWS, ids=[row["name"] for row in ROWS])
def test_a_committed_checkpoint_replays_its_reported_scores(row: dict, server_address: str):
    name = row["name"].removesuffix(NO_MASK)
    use_mask = row["greedy_over"] == "legal actions"
    assert use_mask == (not row["name"].endswith(NO_MASK))
    policy = load(CHECKPOINTS / name)
    assert policy.algorithm == row["algorithm"]
    scores, _ = evaluate_policy(
        policy.act,
        EPISODES,
        seed=1000,
        address=server_address,
        num_envs=EPISODES,
        use_mask=use_mask,
    )
    assert [int(s) for s in scores] == row["scores"][:EPISODES]

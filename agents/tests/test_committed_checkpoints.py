"""The results table's "(no mask)" rows: a committed checkpoint played greedily over all 57
actions replays the scores ``docs/results/results.json`` reports for it on seeds 1000..1009.
(``test_committed.py`` replays every checkpoint's masked row; these rows play another policy,
the argmax over every action, from the same files.)"""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from dinerdash_agents import load
from dinerdash_agents.evaluate import evaluate_policy

RESULTS = Path(__file__).resolve().parents[2] / "docs" / "results"
NO_MASK = " (no mask)"
#: Evaluation episodes replayed per row: seeds 1000..1009 (the table's first ten), one batch.
EPISODES = 10
UNMASKED = [
    row
    for row in json.loads((RESULTS / "results.json").read_text())["agents"]
    if row["name"].endswith(NO_MASK)
]


def test_the_table_has_unmasked_rows() -> None:
    # The paper's plain-loss BC and unmasked PPO rows (their policies over all 57 actions).
    assert len(UNMASKED) >= 3, [row["name"] for row in UNMASKED]
    assert all(row["greedy_over"] == "all 57 actions" for row in UNMASKED)


@pytest.mark.parametrize("row", UNMASKED, ids=[row["name"] for row in UNMASKED])
def test_an_unmasked_row_replays_its_reported_scores(row: dict, server_address: str) -> None:
    policy = load(RESULTS / "checkpoints" / row["name"].removesuffix(NO_MASK))
    assert policy.algorithm == row["algorithm"]
    scores, _ = evaluate_policy(
        policy.act, EPISODES, seed=1000, address=server_address, num_envs=EPISODES, use_mask=False
    )
    assert [int(s) for s in scores] == row["scores"][:EPISODES]
    # The masked policy of the same file plays differently on these seeds: the rows differ.
    masked = next(r for r in _rows() if r["name"] == row["name"].removesuffix(NO_MASK))
    assert masked["scores"] != row["scores"]


def _rows() -> list[dict]:
    return json.loads((RESULTS / "results.json").read_text())["agents"]

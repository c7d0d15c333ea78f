"""Evaluation seeds that cannot touch training seeds by accident: what a checkpoint records it
was trained on, where ``evaluate`` starts when not told (1000, or past the training seeds), and
the warning when told to play on training seeds, through the command against a real server."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from dinerdash_agents import seeds
from dinerdash_agents.cli import main
from dinerdash_agents.dagger import training_seeds
from dinerdash_agents.train_imitation import default_config, train_checkpoint


def test_what_a_checkpoint_records_it_was_trained_on() -> None:
    assert seeds.as_ranges([5, 3, 4, 9, 4, 10]) == [[3, 5], [9, 10]]
    recorded = {"algorithm": "bc", "data": {"seeds": [0, 19], "seed_ranges": [[0, 9], [15, 19]]}}
    assert seeds.trained_on(recorded) == [range(0, 10), range(15, 20)]
    # Written before "seed_ranges": the span of "seeds", less DAgger's skipped seeds.
    assert seeds.trained_on({"algorithm": "bc", "data": {"seeds": [0, 273]}}) == [range(274)]
    dagger = {"algorithm": "dagger", "data": {"seeds": [0, 1299]}}
    assert seeds.trained_on(dagger) == [range(1000), range(1100, 1300)]
    assert sum(map(len, seeds.trained_on(dagger))) == len(training_seeds(0, 1200))
    # Such a span skipped what was reserved then: 2100..2399 were not yet.
    wide = seeds.trained_on({"algorithm": "dagger", "data": {"seeds": [0, 2499]}})
    assert wide == [range(1000), range(1100, 2000), range(2100, 2500)]
    assert seeds.trained_on({"algorithm": "ppo", "data": {}}) == []


def test_the_default_evaluation_keeps_clear_of_the_training_seeds() -> None:
    assert seeds.evaluation_seed([], 100) == 1000
    assert seeds.evaluation_seed([range(274)], 100) == 1000
    assert seeds.evaluation_seed([range(990, 1050)], 100) == 1050
    # Past one range into the next: the first 100 unseen seeds in a row.
    assert seeds.evaluation_seed([range(1000, 1010), range(1060, 1200)], 100) == 1200
    assert seeds.evaluation_seed([range(1000, 1010), range(1200, 1300)], 100) == 1010


def test_the_warning_names_both_ranges() -> None:
    assert seeds.overlap_warning("bc", [range(274)], 1000, 100) is None
    warning = seeds.overlap_warning("bc", [range(274)], 200, 100)
    assert warning is not None
    assert "seeds 200..299, of which 200..273 are seeds bc was trained on (0..273)" in warning


def _scored_seed(out: str) -> int:
    return json.loads(out.strip().splitlines()[-1])["seed"]


def test_evaluate_defaults_to_unseen_seeds_and_warns_on_training_ones(
    expert_demos: Path, server_address: str, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    out = tmp_path / "bc"
    train_checkpoint("bc", expert_demos, out, config=default_config("bc", epochs=1), progress=False)
    described = json.loads((out / "checkpoint.json").read_text())
    assert described["data"]["seed_ranges"] == [[0, 19]]  # the 20 demonstrations' seeds
    quick = ["--episodes", "2", "--max-steps", "30", "--json", "--address", server_address]

    assert main(["evaluate", str(out), *quick]) == 0
    captured = capsys.readouterr()
    assert _scored_seed(captured.out) == 1000
    assert "warning" not in captured.err and "note" not in captured.err

    assert main(["evaluate", str(out), "--seed", "18", *quick]) == 0
    captured = capsys.readouterr()
    assert _scored_seed(captured.out) == 18
    assert "warning: evaluating on seeds 18..19, of which 18..19 are seeds bc was trained on " in (
        captured.err
    )
    assert "(0..19)" in captured.err

    # A checkpoint trained on seeds 995..1000 is evaluated from 1001 unless told otherwise.
    described["data"]["seed_ranges"] = [[0, 19], [995, 1000]]
    (out / "checkpoint.json").write_text(json.dumps(described))
    assert main(["evaluate", str(out), *quick]) == 0
    captured = capsys.readouterr()
    assert _scored_seed(captured.out) == 1001
    assert "note: bc was trained on seeds 0..19, 995..1000: evaluating on the unseen seeds " in (
        captured.err
    )
    assert "warning" not in captured.err


def test_evaluate_help_shows_the_defaults(capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit):
        main(["evaluate", "--help"])
    text = " ".join(capsys.readouterr().out.split())
    assert "episodes to play (default: 100)" in text
    assert "(default: 64)" in text and "(default: 100000)" in text
    assert "(default: the evaluation seeds' first, 1000," in text

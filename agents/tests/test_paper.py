"""``paper``'s bookkeeping on synthetic results: which agents ``--update`` keeps (only rows with
all their training seeds), and the report's paired differences and pooled runs."""

from __future__ import annotations

import numpy as np
import pytest

from dinerdash_agents import paper


def _row(name: str, scores: list[int], runs: list[list[int]] | None = None) -> dict:
    row = {
        "name": name,
        "label": name,
        "paper": None,
        "paper_fraction": None,
        "scores": scores,
        "sd": float(np.std(scores)),
        "mean": float(np.mean(scores)),
        "training_seconds": 1.0,
        "training_cpu_seconds": 1.0,
    }
    if runs is not None:
        row["runs"] = runs
    return row


def test_update_keeps_only_rows_with_all_their_training_seeds() -> None:
    agent = next(a for a in paper.AGENTS if a.name == "bc-274")
    assert agent.training_seeds == paper.FAST_SEEDS > 1
    one = {"agents": [_row("bc-274", [1, 2])]}
    assert not paper._done(agent, one)  # one run where five are wanted: trained again
    five = {"agents": [_row("bc-274", [1, 2], runs=[[1, 2]] * paper.FAST_SEEDS)]}
    assert paper._done(agent, five)
    assert not paper._done(agent, {"agents": []})
    single = next(a for a in paper.AGENTS if a.training_seeds == 1)
    assert paper._done(single, {"agents": [_row(single.name, [1, 2])]})


def test_every_long_run_and_every_comparison_names_a_known_agent() -> None:
    names = {a.name for a in paper.AGENTS}
    assert {n for a, b, _ in paper.COMPARISONS for n in (a, b)} <= names
    # Seed k > 0 of a kick-started PPO starts from the same seed of its start (which must have
    # it, and come before it in the table: it is trained first).
    for kick in (a for a in paper.AGENTS if a.algorithm == "ppo-kickstart"):
        start = paper._start_of(kick)
        assert start.training_seeds >= kick.training_seeds
        assert paper.AGENTS.index(start) < paper.AGENTS.index(kick)


def test_the_report_pools_runs_and_gives_paired_differences(tmp_path) -> None:
    rng = np.random.default_rng(0)
    expert = rng.integers(2_000, 20_000, size=40)
    noisy = lambda f: [int(x) for x in f * expert + rng.normal(0, 200, size=40)]  # noqa: E731
    runs = [noisy(1.0), noisy(1.2)]
    rows = [_row(name, noisy(1.0)) for name in ("dpgm-274", "dpgm-70", "bc-70")]
    rows.append(_row("bc-274", runs[0], runs=runs))
    results = {"expert": {"scores": [int(x) for x in expert]}, "planner": _row("p", noisy(1.5))}
    results["random"] = _row("r", noisy(-0.1))
    results["agents"] = rows
    paper._add_stats(results)
    bc = next(r for r in rows if r["name"] == "bc-274")
    assert bc["stats"]["runs"] == 2
    assert bc["fraction"] == pytest.approx(1.1, abs=0.02)  # the mean of 1.0 and 1.2
    (difference,) = [d for d in results["differences"] if d["b"] == "bc-274"]
    assert difference["a"] == "dpgm-274"
    assert difference["low"] < -0.1 < difference["high"]
    # Only the pairs whose both rows exist are compared.
    assert {(d["a"], d["b"]) for d in results["differences"]} == {
        ("dpgm-274", "bc-274"),
        ("dpgm-70", "bc-70"),
    }


def test_training_seed_k_of_a_long_run_has_its_own_directory_seed_and_bc_start(
    server_address: str, expert_demos, tmp_path
) -> None:
    from dinerdash import ConnectOptions

    from dinerdash_agents import bc, checkpoint
    from dinerdash_agents.train_imitation import train_checkpoint

    job = paper._Job(
        tmp_path,
        expert_demos,
        expert_demos,
        ConnectOptions(address=server_address),
        seed=10,
        rl_steps=1,  # one iteration
        reuse=True,
        tensorboard=tmp_path / "board",
    )
    kick = next(a for a in paper.AGENTS if a.algorithm == "ppo-kickstart")
    # Kick-started PPO's seed 2 starts from BC's seed 2 (a small one here, on 20 episodes).
    start = paper._start_of(kick).directory(tmp_path, 2)
    train_checkpoint("bc", expert_demos, start, config=bc.BCConfig(hidden=64, epochs=1))
    _, description = paper._train_rl(kick, job, 2)
    directory = tmp_path / "checkpoints" / f"{kick.name}-seed2"
    assert checkpoint.read_description(directory) == description
    assert description["config"]["init"] == str(start)
    assert description["config"]["bc_hidden"] == 64
    assert description["training"]["seed"] == 12  # the base seed 10, plus k
    # A run from scratch (no demonstrations, no BC start) of seed 1.
    ppo = next(a for a in paper.AGENTS if a.name == "ppo-masked")
    paper._train_rl(ppo, job, 1)
    assert (tmp_path / "checkpoints" / "ppo-masked-seed1" / checkpoint.DESCRIPTION).is_file()
    # With a directory for the live curves, each run's are under its checkpoint's name.
    for name in (f"{kick.name}-seed2", "ppo-masked-seed1"):
        assert list((tmp_path / "board" / name).glob("events.out.tfevents.*")), name

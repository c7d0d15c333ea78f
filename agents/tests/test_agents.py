"""The agents package against crafted data and a real local server: demonstration slicing, the
masked loss, DPGM's factor-graph probability, checkpoints, the CLI's refusals, and learning."""

from __future__ import annotations

import json
import math
from pathlib import Path

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from dinerdash_agents import CheckpointError, DemosError, checkpoint, load
from dinerdash_agents import dpgm as dpgm_module
from dinerdash_agents.cli import main
from dinerdash_agents.demos import load_demos
from dinerdash_agents.evaluate import evaluate_policy
from dinerdash_agents.supervised import cross_entropy
from dinerdash_agents.train_imitation import default_config, train_checkpoint

EVAL_SEED = 1000


def write_demos(path: Path, lengths: list[int], **override) -> Path:
    """A demonstrations file in ``python -m dinerdash collect``'s layout; step ``i`` has
    observation value ``i`` at index 0 and action ``i % 57``, so slices are recognisable."""
    total = sum(lengths)
    steps = np.arange(total)
    obs = np.zeros((total, 40), np.float32)
    obs[:, 0] = steps
    masks = np.zeros((total, 57), np.bool_)
    masks[:, 0] = True
    masks[steps, steps % 57] = True
    fields = {
        "observations": obs,
        "actions": (steps % 57).astype(np.int64),
        "action_masks": masks,
        "episode_lengths": np.array(lengths, np.int64),
        "episode_starts": np.concatenate([[0], np.cumsum(lengths)[:-1]]).astype(np.int64),
        "seeds": np.arange(len(lengths), dtype=np.uint64),
        "scores": np.zeros(len(lengths), np.int64),
    }
    fields.update(override)
    fields = {k: v for k, v in fields.items() if v is not None}
    np.savez_compressed(path, **fields)
    return path


# ---- demonstrations ----


def test_first_k_episodes_are_the_first_steps(tmp_path: Path) -> None:
    path = write_demos(tmp_path / "d.npz", [3, 5, 4])
    two = load_demos(path, 2)
    assert (two.episodes, two.available, two.steps) == (2, 3, 8)
    assert two.observations[:, 0].tolist() == list(range(8))
    assert two.actions.tolist() == list(range(8))
    assert two.episode_lengths.tolist() == [3, 5]
    assert load_demos(path).steps == 12


@pytest.mark.parametrize(
    ("make", "words"),
    [
        (lambda p: p / "missing.npz", ["missing.npz", "does not exist"]),
        (
            lambda p: _write_bytes(p / "corrupt.npz", b"not a zip"),
            ["corrupt.npz", "not a readable"],
        ),
        (
            lambda p: write_demos(p / "noact.npz", [3], actions=None),
            ["noact.npz", "'actions'"],
        ),
        (
            lambda p: write_demos(p / "short.npz", [3], episode_lengths=np.array([2])),
            ["short.npz", "'episode_lengths'"],
        ),
    ],
)
def test_bad_demonstrations_name_the_file_and_field(tmp_path: Path, make, words) -> None:
    path = make(tmp_path)
    with pytest.raises(DemosError) as e:
        load_demos(path, 1)
    for word in words:
        assert word in str(e.value)


def _write_bytes(path: Path, data: bytes) -> Path:
    path.write_bytes(data)
    return path


def test_more_episodes_than_the_file_holds_is_refused(tmp_path: Path) -> None:
    path = write_demos(tmp_path / "d.npz", [3, 5])
    with pytest.raises(DemosError, match=r"--episodes 3 .* holds \(2 episodes\)"):
        load_demos(path, 3)


# ---- the loss ----


def test_masked_cross_entropy_is_over_the_legal_actions_only() -> None:
    logits = np.array([[1.0, 2.0, 3.0], [0.5, -1.0, 4.0]], np.float32)
    mask = np.array([[True, True, False], [True, False, True]])
    actions = np.array([1, 0])
    # By hand: row 0 softmax over {1, 2}: -log(e^2 / (e^1 + e^2)); row 1 over {0.5, 4}.
    by_hand = (
        -(
            math.log(math.exp(2) / (math.exp(1) + math.exp(2)))
            + math.log(math.exp(0.5) / (math.exp(0.5) + math.exp(4)))
        )
        / 2
    )
    got = float(cross_entropy(jnp.asarray(logits), jnp.asarray(actions), jnp.asarray(mask)))
    assert got == pytest.approx(by_hand, rel=1e-5)
    plain = (
        -(
            math.log(math.exp(2) / sum(math.exp(v) for v in (1, 2, 3)))
            + math.log(math.exp(0.5) / sum(math.exp(v) for v in (0.5, -1, 4)))
        )
        / 2
    )
    got_plain = float(cross_entropy(jnp.asarray(logits), jnp.asarray(actions), None))
    assert got_plain == pytest.approx(plain, rel=1e-5)


# ---- DPGM's factor graph ----


def test_dpgm_probability_of_going_to_a_table_matches_the_hand_computed_value() -> None:
    # Table 1 ready to order (status 2), its group at patience level 3, empty hands; the mask
    # says "go to table 1" is legal.
    obs = np.zeros((1, 40), np.float32)
    obs[0, 0:3] = [2, 4, 3]
    mask = np.zeros((1, 57), np.bool_)
    mask[0, [0, 1]] = True
    model = dpgm_module.init(dpgm_module.DPGMConfig(), 0)
    theta = np.random.default_rng(0).normal(size=(dpgm_module.CELLS, 2)).astype(np.float32)
    model = eqx.tree_at(lambda m: m.theta, model, jnp.asarray(theta))
    # Action 1's factors: (legal1, status1), (status1, table_patience1),
    # (status1, hand_items, food_in_hand1); mixed radix, first variable most significant.
    off = dpgm_module.factor_offsets(1)
    assert [f.variables for f in dpgm_module.FACTORS if f.action == 1] == [
        ("legal1", "status1"),
        ("status1", "table_patience1"),
        ("status1", "hand_items", "food_in_hand1"),
    ]
    rows = [off[0] + 1 * 7 + 2, off[1] + 2 * 6 + (3 + 1), off[2] + (2 * 3 + 0) * 2 + 0]
    on = math.prod(math.exp(theta[r, 1]) for r in rows)
    off_ = math.prod(math.exp(theta[r, 0]) for r in rows)
    p = eqx.filter_jit(model.action_probabilities)(jnp.asarray(obs), jnp.asarray(mask))
    assert float(p[0, 1]) == pytest.approx(on / (off_ + on), rel=1e-5)


def test_every_action_has_its_own_factor_graph() -> None:
    actions = {f.action for f in dpgm_module.FACTORS}
    assert actions == set(range(57))
    for f in dpgm_module.FACTORS:
        assert all(v in dpgm_module.VARIABLES for v in f.variables)


# ---- checkpoints ----


@pytest.mark.parametrize("algorithm", ["bc", "dpgm"])
def test_checkpoint_round_trip_gives_the_same_actions(tmp_path: Path, algorithm: str) -> None:
    # Random parameters everywhere (DPGM's tables start at zero; training is the learning test's
    # job): every leaf must survive the round trip for the actions to match.
    config = default_config(algorithm)
    model = checkpoint.lookup(algorithm).init(config, 0)
    rng = np.random.default_rng(1)
    model = jax.tree_util.tree_map(
        lambda leaf: (
            jnp.asarray(rng.normal(size=leaf.shape), leaf.dtype) if eqx.is_array(leaf) else leaf
        ),
        model,
    )
    out = tmp_path / algorithm
    checkpoint.save(out, model, {"algorithm": algorithm, "config": config.to_json()})
    policy = checkpoint.Policy(model, {"algorithm": algorithm})
    loaded = load(out)
    assert loaded.algorithm == algorithm
    obs = rng.integers(0, 5, size=(32, 40)).astype(np.float32)
    mask = rng.random((32, 57)) < 0.3
    mask[:, 0] = True
    assert np.array_equal(policy.act(obs, mask), loaded.act(obs, mask))
    assert np.array_equal(policy.act(obs), loaded.act(obs))
    assert all(mask[i, a] for i, a in enumerate(loaded.act(obs, mask)))


def test_the_algorithm_table_is_the_one_source_of_every_checkpoint() -> None:
    """``checkpoint.ALGORITHMS`` names every algorithm once, with the module that holds its
    hooks; every committed checkpoint's algorithm is in it, and a checkpoint that records its
    module (``"module"``) records the table's. Policies answer the one shape, ``predict``."""
    import importlib

    for name in checkpoint.ALGORITHMS:
        entry = checkpoint.lookup(name)
        assert isinstance(importlib.import_module(entry.module).CHECKPOINT, checkpoint.Hooks)
        assert entry.module == checkpoint.module_of(name)
    committed = Path(__file__).resolve().parents[2] / "docs" / "results" / "checkpoints"
    descriptions = [checkpoint.read_description(d) for d in sorted(committed.iterdir())]
    assert len(descriptions) >= 74
    for d in descriptions:
        assert d["algorithm"] in checkpoint.ALGORITHMS
        assert d.get("module", checkpoint.module_of(d["algorithm"])) == checkpoint.module_of(
            d["algorithm"]
        )
    with pytest.raises(CheckpointError, match="known: bc, dagger"):
        checkpoint.lookup("sac")


def test_a_policy_predicts_with_its_state_as_sb3s_do(tmp_path: Path) -> None:
    config = default_config("bc")
    model = checkpoint.lookup("bc").init(config, 0)
    policy = checkpoint.Policy(model, {"algorithm": "bc", "config": config.to_json()})
    rng = np.random.default_rng(2)
    obs = rng.integers(0, 5, size=(8, 40)).astype(np.float32)
    mask = rng.random((8, 57)) < 0.3
    mask[:, 0] = True
    actions, state = policy.predict(obs, None, np.ones(8, bool), action_masks=mask)
    assert state is None  # feed-forward
    assert np.array_equal(actions, policy.act(obs, mask))


def test_checkpoint_of_another_algorithm_or_version_is_refused(tmp_path: Path) -> None:
    demos = write_demos(tmp_path / "d.npz", [30])
    out = tmp_path / "bc"
    train_checkpoint("bc", demos, out, config=default_config("bc", epochs=1), progress=False)
    with pytest.raises(CheckpointError, match="'algorithm' is 'bc', expected 'dpgm'"):
        load(out, algorithm="dpgm")
    described = json.loads((out / "checkpoint.json").read_text())
    (out / "checkpoint.json").write_text(json.dumps({**described, "format_version": 99}))
    with pytest.raises(CheckpointError, match="'format_version' is 99"):
        load(out)
    (out / "checkpoint.json").write_text(json.dumps({**described, "algorithm": "sac"}))
    with pytest.raises(CheckpointError, match="'algorithm' is 'sac'"):
        load(out)
    # A known algorithm whose config does not fit (a BC config labelled PPO).
    (out / "checkpoint.json").write_text(json.dumps({**described, "algorithm": "ppo"}))
    with pytest.raises(CheckpointError, match="'config' does not fit ppo"):
        load(out)
    (out / "checkpoint.json").write_text(json.dumps(described))
    (out / "model.eqx").write_bytes(b"\x00\x01")
    with pytest.raises(CheckpointError, match=r"model\.eqx"):
        load(out)


# ---- the CLI's refusals: a clear error, exit 1, nothing written ----


def test_train_with_bad_demonstrations_exits_1_and_writes_nothing(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    out = tmp_path / "runs" / "bc"
    assert main(["train", "bc", "--demos", str(tmp_path / "none.npz"), "--out", str(out)]) == 1
    assert "none.npz" in capsys.readouterr().err
    demos = write_demos(tmp_path / "d.npz", [10, 10])
    argv = ["train", "dpgm", "--demos", str(demos), "--episodes", "5", "--out", str(out)]
    assert main(argv) == 1
    assert "--episodes 5" in capsys.readouterr().err
    assert not out.parent.exists()


def test_evaluate_against_an_unreachable_server_exits_1(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    demos = write_demos(tmp_path / "d.npz", [20])
    out = tmp_path / "bc"
    train_checkpoint("bc", demos, out, config=default_config("bc", epochs=1), progress=False)
    # Port 1 on loopback: nothing listens there.
    argv = ["evaluate", str(out), "--episodes", "1", "--address", "127.0.0.1:1"]
    assert main(argv) == 1
    assert "127.0.0.1:1" in capsys.readouterr().err
    assert main(["evaluate", str(tmp_path / "nothing")]) == 1
    assert "nothing" in capsys.readouterr().err


# ---- learning, against a real server ----


def test_bc_and_dpgm_learn_from_20_expert_episodes(
    expert_demos: Path, server_address: str, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    episodes = 4
    random_scores, _ = evaluate_policy(
        lambda obs, mask: np.random.default_rng(0).integers(0, 57, size=len(obs)),
        episodes,
        seed=EVAL_SEED,
        address=server_address,
    )
    budgets = {"bc": default_config("bc", epochs=3), "dpgm": default_config("dpgm", epochs=2)}
    for algorithm, config in budgets.items():
        out = tmp_path / algorithm
        train_checkpoint(algorithm, expert_demos, out, config=config, progress=False)
        argv = ["evaluate", str(out), "--episodes", str(episodes), "--seed", str(EVAL_SEED)]
        assert main([*argv, "--address", server_address, "--json"]) == 0
        lines = capsys.readouterr().out.splitlines()
        assert lines[0].startswith(f"policy {algorithm}: {episodes} episodes (seeds 1000..=1003)")
        result = json.loads(lines[-1])
        assert set(result) == {"policy", "seed", "scores", "lengths", "mean", "sd"}
        assert len(result["scores"]) == episodes
        # Random play loses its five groups fast (about -1,300); the expert scores about 9,000.
        assert result["mean"] > max(random_scores.mean(), 0) + 3000, (algorithm, result)

"""DPGM, Decomposed Policy Graph Modelling (the paper's method): one factor graph per action over
that action's own sub-state, then re-weighting layers over the 57 action scores.

For action ``k`` the model is a factor graph over discrete sub-state variables ``x`` and the binary
``y`` = "the expert takes k": ``p(x, y) = (1/Z) prod_i phi_i(x_i, y)`` with table potentials
``phi_i(x_i, y) = exp theta_i[x_i, y]``, so the action's score is

    p_k = prod_i phi_i(x_i, 1) / (prod_i phi_i(x_i, 0) + prod_i phi_i(x_i, 1))
        = sigmoid(sum_i theta_i[x_i, 1] - theta_i[x_i, 0]).

Every factor owns a table with one row per joint value of its variables (mixed radix, first
variable most significant) and two columns (y = 0, y = 1); all tables live in one array ``theta``
of shape (cells, 2). Which variables each action reads, and how they are grouped into factors,
is the domain knowledge of :func:`factor_layout` (docs/agents.md says why, family by family).

Training (Algorithm 1 of the paper, then its end-to-end step):
  1. every demonstration step is an example for every action (y = 1 when the expert took it);
     the tables minimise the squared loss sum_t (p_k(x_t) - y_t)^2;
  2. the re-weighting layers (FC 512, ReLU, FC 57) learn from the 57 scores with cross-entropy
     on the expert's action, the tables frozen;
  3. the whole model is fine-tuned end to end with the same cross-entropy.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import asdict, dataclass, replace
from typing import NamedTuple

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from dinerdash.game import (
    DROP_DISHES,
    FIRST_PICK_UP,
    FIRST_SEAT,
    HAND_IN_ORDERS,
    NUM_ACTIONS,
    NUM_TABLES,
    QUEUE_CAPACITY,
    WAIT,
    seat_action,
)

from . import checkpoint
from .demos import Demos
from .supervised import cross_entropy, fit

__all__ = [
    "DPGM",
    "FACTORS",
    "VARIABLES",
    "DPGMConfig",
    "Factor",
    "factor_cells",
    "init",
    "sub_state",
    "train",
]

MAX_ARITY = 3


# ---- the sub-state variables (all discrete), read from the observation and the action mask ----

#: (family, how many, values): the variables in the column order of :func:`sub_state`, which
#: computes each family as one block (one array operation rather than one per column).
_FAMILIES: list[tuple[str, int, int]] = [
    ("none", 1, 1),
    ("status", NUM_TABLES, 7),  # 0 free .. 6 waiting for the bill
    ("table_patience", NUM_TABLES, 6),  # P div 200 of the seated group, -1..4 shifted to 0..5
    ("capacity", NUM_TABLES, 7),
    ("food_ready", NUM_TABLES, 2),  # the table's food is on a counter
    ("food_in_hand", NUM_TABLES, 2),
    ("group_waiting", QUEUE_CAPACITY, 2),
    ("group_size", QUEUE_CAPACITY, 7),
    ("group_patience", QUEUE_CAPACITY, 5),  # P div 200, 0..4
    ("hand_items", 1, 3),
    ("hand_orders", 1, 3),
    ("hand_dishes", 1, 3),
    ("legal", NUM_ACTIONS, 2),  # the action's preconditions hold (docs/rules.md section 7)
    ("legal_others", 1, 5),  # legal actions other than wait, 4 meaning 4 or more
    ("legal_tables", 1, 4),  # legal go-to-table actions, 3 meaning 3 or more
    ("legal_seats", 1, 4),  # legal seating actions, 3 meaning 3 or more
]

#: name -> number of values, in column order: tables and groups numbered from 1 ("status3",
#: "group_size1"), actions from 0 ("legal15").
VARIABLES: dict[str, int] = {}
for _family, _count, _values in _FAMILIES:
    if _count == 1:
        VARIABLES[_family] = _values
    else:
        _first = 0 if _family == "legal" else 1
        for _i in range(_first, _first + _count):
            VARIABLES[f"{_family}{_i}"] = _values
_COLUMN = {name: i for i, name in enumerate(VARIABLES)}
_CARDINALITIES = np.array(list(VARIABLES.values()), np.int32)


def sub_state(obs: jax.Array, mask: jax.Array) -> jax.Array:
    """Every sub-state variable of a batch, (B, len(VARIABLES)) int32, clipped to its range."""
    o = jnp.round(obs).astype(jnp.int32)
    m = mask.astype(jnp.int32)
    hands = o[:, 38:40]
    tables = o[:, :18].reshape(-1, NUM_TABLES, 3)  # status, capacity, patience level
    queue = o[:, 24:38].reshape(-1, QUEUE_CAPACITY, 2)  # patience level, size
    in_hand = hands[:, None, :] == 7 + jnp.arange(NUM_TABLES)[None, :, None]  # food(t) is 6 + t

    def one(x: jax.Array) -> jax.Array:
        return x[:, None]

    blocks = {
        "none": jnp.zeros_like(o[:, :1]),
        "status": tables[:, :, 0],
        "table_patience": tables[:, :, 2] + 1,
        "capacity": tables[:, :, 1],
        "food_ready": o[:, 18:24],
        "food_in_hand": jnp.any(in_hand, axis=2).astype(jnp.int32),
        "group_waiting": (queue[:, :, 1] > 0).astype(jnp.int32),
        "group_size": queue[:, :, 1],
        "group_patience": queue[:, :, 0],
        "hand_items": one(jnp.sum(hands > 0, axis=1)),
        "hand_orders": one(jnp.sum((hands >= 1) & (hands <= 6), axis=1)),
        "hand_dishes": one(jnp.sum(hands >= 13, axis=1)),
        "legal": m,
        "legal_others": one(jnp.sum(m[:, 1:], axis=1)),
        "legal_tables": one(jnp.sum(m[:, 1:7], axis=1)),
        "legal_seats": one(jnp.sum(m[:, FIRST_SEAT:], axis=1)),
    }
    x = jnp.concatenate([blocks[family] for family, _, _ in _FAMILIES], axis=1)
    return jnp.clip(x, 0, jnp.asarray(_CARDINALITIES) - 1)


# ---- the factors of every action ----


class Factor(NamedTuple):
    action: int
    variables: tuple[str, ...]


def factor_layout() -> list[Factor]:
    """The factor graph of each of the 57 actions (docs/agents.md gives the reasons)."""
    f: list[Factor] = []
    # wait: memorised over how much else could be done.
    f.append(Factor(WAIT, ("legal_others",)))
    f.append(Factor(WAIT, ("legal_tables", "legal_seats")))
    # go to table t: what the visit would do depends on the status; the hurry on the patience;
    # whether it is possible on the hands (an order or dishes need a free hand, serving needs
    # the table's food in hand).
    for t in range(1, NUM_TABLES + 1):
        f.append(Factor(t, (f"legal{t}", f"status{t}")))
        f.append(Factor(t, (f"status{t}", f"table_patience{t}")))
        f.append(Factor(t, (f"status{t}", "hand_items", f"food_in_hand{t}")))
    # hand orders to the kitchen: memorised over the hands.
    f.append(Factor(HAND_IN_ORDERS, (f"legal{HAND_IN_ORDERS}", "hand_orders", "hand_items")))
    # pick up food of t: memorised over counter and hands; the table's hurry as its own factor.
    for t in range(1, NUM_TABLES + 1):
        a = FIRST_PICK_UP + t - 1
        f.append(Factor(a, (f"legal{a}", "hand_items", f"food_ready{t}")))
        f.append(Factor(a, (f"status{t}", f"table_patience{t}")))
    # drop dishes: memorised over the hands.
    f.append(Factor(DROP_DISHES, (f"legal{DROP_DISHES}", "hand_dishes", "hand_items")))
    # seat group g at table t: the paper's four numbers (table status and size, group size and
    # patience), in three factors: can it be done, does the group fit the table, how urgent.
    for g in range(1, QUEUE_CAPACITY + 1):
        for t in range(1, NUM_TABLES + 1):
            a = seat_action(g, t)
            f.append(Factor(a, (f"legal{a}", f"status{t}")))
            f.append(Factor(a, (f"capacity{t}", f"group_size{g}")))
            f.append(Factor(a, (f"group_waiting{g}", f"group_patience{g}")))
    return f


FACTORS: list[Factor] = factor_layout()


def _layout_arrays(factors: list[Factor]) -> tuple[np.ndarray, np.ndarray, np.ndarray, int]:
    """Columns, mixed-radix strides and table offsets of every factor, padded to MAX_ARITY with
    the one-valued variable ``none``; and the number of table rows in all."""
    cols = np.zeros((len(factors), MAX_ARITY), np.int32)
    strides = np.zeros((len(factors), MAX_ARITY), np.int32)
    offsets = np.zeros(len(factors), np.int32)
    cells = 0
    for i, factor in enumerate(factors):
        names = list(factor.variables) + ["none"] * (MAX_ARITY - len(factor.variables))
        stride = 1
        for j in reversed(range(MAX_ARITY)):
            cols[i, j] = _COLUMN[names[j]]
            strides[i, j] = stride
            stride *= VARIABLES[names[j]]
        offsets[i] = cells
        cells += stride
    return cols, strides, offsets, cells


_COLS, _STRIDES, _OFFSETS, CELLS = _layout_arrays(FACTORS)
_OF_ACTION = np.zeros((len(FACTORS), NUM_ACTIONS), np.float32)
_OF_ACTION[np.arange(len(FACTORS)), [f.action for f in FACTORS]] = 1.0


def factor_offsets(action: int) -> list[int]:
    """The first table row of each factor of ``action``, in :data:`FACTORS` order."""
    return [int(_OFFSETS[i]) for i, f in enumerate(FACTORS) if f.action == action]


def factor_cells(obs: jax.Array, mask: jax.Array) -> jax.Array:
    """The table row each factor reads in each state: (B, len(FACTORS)) int32."""
    x = sub_state(obs, mask)
    values = x[:, _COLS]  # (B, F, MAX_ARITY)
    return jnp.asarray(_OFFSETS) + jnp.sum(values * jnp.asarray(_STRIDES), axis=-1)


@dataclass(frozen=True)
class DPGMConfig:
    reweight_hidden: int = 512
    loss: str = "masked"  # "masked" | "plain": the softmax of stages 2 and 3
    graph_epochs: int = 2
    reweight_epochs: int = 5
    finetune_epochs: int = 5
    batch_size: int = 512
    graph_learning_rate: float = 0.05
    learning_rate: float = 1e-3
    finetune_learning_rate: float = 3e-4
    #: the factor layout this checkpoint was trained with (checked on load)
    factors: int = len(FACTORS)
    cells: int = CELLS

    def to_json(self) -> dict:
        return asdict(self)

    @property
    def total_epochs(self) -> int:
        return self.graph_epochs + self.reweight_epochs + self.finetune_epochs

    def with_epochs(self, epochs: int) -> DPGMConfig:
        """This config with ``epochs`` epochs in each of the three stages."""
        return replace(self, graph_epochs=epochs, reweight_epochs=epochs, finetune_epochs=epochs)


class DPGM(eqx.Module):
    """The 57 factor graphs (one table array) and the re-weighting layers."""

    theta: jax.Array  # (CELLS, 2): log-potentials theta_i[x_i, y]
    reweight: eqx.nn.Linear
    out: eqx.nn.Linear

    def __init__(self, config: DPGMConfig, key: jax.Array) -> None:
        k1, k2 = jax.random.split(key)
        self.theta = jnp.zeros((CELLS, 2), jnp.float32)  # every p_k starts at 1/2
        self.reweight = eqx.nn.Linear(NUM_ACTIONS, config.reweight_hidden, key=k1)
        self.out = eqx.nn.Linear(config.reweight_hidden, NUM_ACTIONS, key=k2)

    def action_probabilities(self, obs: jax.Array, mask: jax.Array) -> jax.Array:
        """p_k = p(y_k = 1 | x_k) of every action's factor graph: (B, 57)."""
        cells = factor_cells(obs, mask)
        theta = self.theta[cells]  # (B, F, 2)
        log_odds = (theta[..., 1] - theta[..., 0]) @ jnp.asarray(_OF_ACTION)
        return jax.nn.sigmoid(log_odds)

    def __call__(
        self, obs: jax.Array, mask: jax.Array | None = None, key: jax.Array | None = None
    ) -> jax.Array:
        """Action logits (B, 57) after re-weighting. The action mask is an input (the legality
        variables of the sub-states); without one every action counts as legal."""
        del key
        if mask is None:
            mask = jnp.ones((obs.shape[0], NUM_ACTIONS), jnp.bool_)
        p = self.action_probabilities(obs, mask)
        h = jax.nn.relu(jax.vmap(self.reweight)(p))
        return jax.vmap(self.out)(h)


def init(config: DPGMConfig, seed: int = 0) -> DPGM:
    return DPGM(config, jax.random.PRNGKey(seed))


def train(
    demos: Demos,
    config: DPGMConfig,
    *,
    seed: int = 0,
    on_epoch: Callable[[str, int, float], None] | None = None,
) -> tuple[DPGM, dict]:
    """DPGM fitted to ``demos`` in the three stages of the module doc; returns the model and the
    per-epoch losses of each stage."""
    model = init(config, seed)
    use_mask = config.loss == "masked"
    data = {"obs": demos.observations, "action": demos.actions, "mask": demos.action_masks}

    def report(stage: str):
        return None if on_epoch is None else (lambda e, loss: on_epoch(stage, e, loss))

    def graph_loss(model, batch, key):
        p = model.action_probabilities(batch["obs"], batch["mask"])
        y = jax.nn.one_hot(batch["action"], NUM_ACTIONS)
        return jnp.mean(jnp.sum((p - y) ** 2, axis=-1))

    def policy_loss(model, batch, key):
        logits = model(batch["obs"], batch["mask"])
        return cross_entropy(logits, batch["action"], batch["mask"] if use_mask else None)

    def only_theta(m):
        spec = jax.tree_util.tree_map(lambda _: False, m)
        return eqx.tree_at(lambda s: s.theta, spec, replace=True)

    def all_but_theta(m):
        spec = jax.tree_util.tree_map(eqx.is_array, m)
        return eqx.tree_at(lambda s: s.theta, spec, replace=False)

    common = {"batch_size": config.batch_size, "seed": seed}
    model, graph = fit(
        model,
        graph_loss,
        data,
        epochs=config.graph_epochs,
        learning_rate=config.graph_learning_rate,
        trainable=only_theta,
        on_epoch=report("dpgm graphs"),
        **common,
    )
    model, reweight = fit(
        model,
        policy_loss,
        data,
        epochs=config.reweight_epochs,
        learning_rate=config.learning_rate,
        trainable=all_but_theta,
        on_epoch=report("dpgm re-weighting"),
        **common,
    )
    model, finetune = fit(
        model,
        policy_loss,
        data,
        epochs=config.finetune_epochs,
        learning_rate=config.finetune_learning_rate,
        on_epoch=report("dpgm end to end"),
        **common,
    )
    return model, {
        "graph_squared": graph,
        "reweight_cross_entropy": reweight,
        "finetune_cross_entropy": finetune,
    }


def config_from_json(values: dict) -> DPGMConfig:
    return DPGMConfig(**values)


def check(config: DPGMConfig) -> str | None:
    """Why a checkpoint of ``config`` cannot be loaded here: a factor layout of another version."""
    if (config.factors, config.cells) == (len(FACTORS), CELLS):
        return None
    return (
        f"has {config.factors} factors and {config.cells} cells; this version's factor layout "
        f"has {len(FACTORS)} and {CELLS}"
    )


#: What :func:`~dinerdash_agents.checkpoint.load` needs of a ``dpgm`` checkpoint.
CHECKPOINT = checkpoint.Hooks(config_from_json=config_from_json, init=init, check=check)

"""The game's fixed numbers, ruleset ``v0`` (docs/rules.md), defined once for the client and the
code built on it. Code with an environment reads the observation's bounds from its
``observation_space`` (the server's Spec); :data:`OBSERVATION_LOW` and :data:`OBSERVATION_HIGH`
are for what has no server to ask.
"""

from __future__ import annotations

import numpy as np
from gymnasium import spaces

from ._proto import pb

__all__ = [
    "DROP_DISHES",
    "FIRST_PICK_UP",
    "FIRST_SEAT",
    "HAND_IN_ORDERS",
    "NUM_ACTIONS",
    "NUM_TABLES",
    "OBSERVATION_HIGH",
    "OBSERVATION_LOW",
    "OBSERVATION_SIZE",
    "QUEUE_CAPACITY",
    "RULESET",
    "WAIT",
    "observation_space",
    "seat_action",
]

#: The ruleset this client speaks.
RULESET = "v0"

#: Tables in the restaurant, and waiting groups the queue (and the observation) holds.
NUM_TABLES = 6
QUEUE_CAPACITY = 7

#: Number of actions (docs/rules.md section 4.1): wait, go to table 1..6, hand in the orders, pick
#: up the food of table 1..6, drop the dishes, seat waiting group g at table t.
NUM_ACTIONS = 57
WAIT = 0
HAND_IN_ORDERS = 7
FIRST_PICK_UP = 8
DROP_DISHES = 14
FIRST_SEAT = 15

#: Observation length (docs/rules.md section 6): status, capacity and patience level of each
#: table, whose food is on a counter, patience level and size of each waiting group, two hands.
OBSERVATION_SIZE = 40

#: The inclusive bounds of each observation index that a ruleset ``v0`` server sends in its Spec.
OBSERVATION_LOW = np.array(
    [0, 0, -1] * NUM_TABLES + [0] * NUM_TABLES + [0, 0] * QUEUE_CAPACITY + [0, 0], dtype=np.float32
)
OBSERVATION_HIGH = np.array(
    [6, 6, 4] * NUM_TABLES + [1] * NUM_TABLES + [4, 6] * QUEUE_CAPACITY + [18, 18], dtype=np.float32
)
OBSERVATION_LOW.flags.writeable = False
OBSERVATION_HIGH.flags.writeable = False


def seat_action(group: int, table: int) -> int:
    """The action "seat waiting group ``group`` at table ``table``" (both numbered from 1)."""
    return FIRST_SEAT + NUM_TABLES * (group - 1) + (table - 1)


def observation_space(spec: pb.Spec | None = None) -> spaces.Box:
    """The observation Box with the bounds the server reports in ``spec`` (docs/rules.md section 6);
    without a Spec, those of ruleset ``v0``."""
    if spec is None:
        return spaces.Box(low=OBSERVATION_LOW, high=OBSERVATION_HIGH, dtype=np.float32)
    if spec.observation_size != OBSERVATION_SIZE or spec.num_actions != NUM_ACTIONS:
        raise RuntimeError(
            f"the server reports {spec.observation_size} observations and {spec.num_actions} "
            f"actions; this client knows {OBSERVATION_SIZE} and {NUM_ACTIONS} "
            f"(ruleset {RULESET})"
        )
    low = np.asarray(spec.observation_low, dtype=np.float32)
    high = np.asarray(spec.observation_high, dtype=np.float32)
    return spaces.Box(low=low, high=high, dtype=np.float32)

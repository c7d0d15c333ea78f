"""A plain-Python simulator of Diner Dash, ruleset ``v0`` (a port of ``server/src/sim/``): the
baseline of ``python -m dinerdash bench``, written as a straightforward Python game is (objects,
lists, ``random.Random``; no numpy, neither tuned nor slowed down), so that its speed is a Python
simulator's (docs/benchmarks.md#the-python-client). ``tests/test_reference.py`` matches it step
for step, the expert's choices included, against the recorded reference trajectories. The
Gymnasium environments never use it.
"""

from __future__ import annotations

import random
import time
from dataclasses import dataclass
from typing import NamedTuple

from dinerdash.game import (
    DROP_DISHES,
    FIRST_PICK_UP,
    FIRST_SEAT,
    HAND_IN_ORDERS,
    NUM_ACTIONS,
    NUM_TABLES,
    QUEUE_CAPACITY,
    WAIT,
)

__all__ = [
    "TABLE_CAPACITIES",
    "Config",
    "Game",
    "Group",
    "Item",
    "Restaurant",
    "Table",
    "random_steps_per_second",
]

TABLE_CAPACITIES = (4, 4, 2, 6, 4, 4)
NUM_COUNTERS = 5
HAND_CAPACITY = 2
# Each reset draws this many (type, size) pairs; later groups repeat the list (docs/rules.md §2).
ARRIVALS_PER_EPISODE = 200

# Table statuses (docs/rules.md §1).
FREE = 0
READING = 1
READY_TO_ORDER = 2
WAITING_FOR_FOOD = 3
EATING = 4
DISHES = 5
WAITING_FOR_BILL = 6

# What a hand slot shows in the observation: the item's offset plus its table (0 = empty hand).
_ITEM_OFFSET = {"order": 0, "food": 6, "dish": 12}

# Random steps run before the clock starts, so that the measurement skips the first calls' costs.
WARMUP_STEPS = 1_000


@dataclass(frozen=True)
class Config:
    """The numbers of one game; the defaults are ruleset ``v0`` (the server's defaults too)."""

    arrival_interval: int = 8
    patience: tuple[int, int] = (600, 800)
    decay: tuple[int, int] = (12, 7)
    reading_ticks: int = 10
    cooking_ticks: int = 10
    eating_ticks: int = 10
    lives: int = 5
    # Steps after which an episode is truncated; 0: no limit (the reference has none).
    time_limit: int = 0


class Item(NamedTuple):
    """Something in the waiter's hands: an ``"order"``, ``"food"`` or ``"dish"`` of a table."""

    kind: str
    table: int


@dataclass
class Group:
    """A group of customers, waiting or seated."""

    customer_type: int
    size: int
    patience: int
    buffer: int = 100

    def decay(self, config: Config) -> bool:
        """One tick of impatience; returns whether the group has run out of patience."""
        d = config.decay[self.customer_type - 1]
        self.buffer -= d
        if self.buffer < 0:
            # The overshoot is not carried into P (docs/rules.md §5.1).
            self.patience -= d
            self.buffer = 0
        return self.patience <= 0

    def copy(self) -> Group:
        return Group(self.customer_type, self.size, self.patience, self.buffer)


@dataclass
class Table:
    """One table: its status and, while a group sits there, the group."""

    capacity: int
    status: int = FREE
    group: Group | None = None
    # Tick at which reading (status 1) or eating (status 4) started.
    since: int = 0

    def copy(self) -> Table:
        group = self.group.copy() if self.group is not None else None
        return Table(self.capacity, self.status, group, self.since)


@dataclass
class Order:
    """An order handed to the kitchen."""

    table: int
    placed: int


def _shaping(patience: int, divisor: int) -> int:
    """The expert's bonus for serving an impatient group (docs/rules.md §8)."""
    return round((700 - patience) / divisor) if patience < 700 else 0


class Restaurant:
    """The whole state of one episode: tables, queue, counters, hands, kitchen, clock and score.

    Nothing here draws random numbers (the episode's arrival list is given), so a copy is a
    complete future: the expert's look-ahead relies on it.
    """

    def __init__(self, config: Config, arrivals: list[tuple[int, int]]) -> None:
        self.config = config
        self.arrivals = arrivals
        self.arrived = 0
        self.now = 0
        self.score = 0
        self.lost = 0
        self.next_arrival = 0
        self.tables = [Table(capacity) for capacity in TABLE_CAPACITIES]
        self.queue: list[Group] = []
        # Each slot is 0 (empty) or the table whose food lies there.
        self.counters = [0] * NUM_COUNTERS
        self.hands: list[Item] = []
        self.orders: list[Order] = []
        # The first group walks in at once (docs/rules.md §3).
        self._arrive()

    def copy(self) -> Restaurant:
        other = Restaurant.__new__(Restaurant)
        other.__dict__.update(self.__dict__)
        other.tables = [table.copy() for table in self.tables]
        other.queue = [group.copy() for group in self.queue]
        other.counters = list(self.counters)
        other.hands = list(self.hands)
        other.orders = [Order(o.table, o.placed) for o in self.orders]
        return other

    @property
    def terminated(self) -> bool:
        return self.lost >= self.config.lives

    @property
    def truncated(self) -> bool:
        return self.config.time_limit != 0 and self.now >= self.config.time_limit

    def step(self, action: int) -> int:
        """The action, then one tick of time; returns the change of the score."""
        before = self.score
        self._apply(action, shaped=False)
        self._advance()
        return self.score - before

    def is_legal(self, action: int) -> bool:
        """Whether the action's preconditions hold (docs/rules.md §4.1)."""
        free_hand = len(self.hands) < HAND_CAPACITY
        if action == WAIT:
            return True
        if 1 <= action <= 6:
            status = self.tables[action - 1].status
            if status in (READY_TO_ORDER, DISHES):
                return free_hand
            if status == WAITING_FOR_FOOD:
                return Item("food", action) in self.hands
            return status == WAITING_FOR_BILL
        if action == HAND_IN_ORDERS:
            return any(item.kind == "order" for item in self.hands)
        if FIRST_PICK_UP <= action < DROP_DISHES:
            return free_hand and action - FIRST_PICK_UP + 1 in self.counters
        if action == DROP_DISHES:
            return any(item.kind == "dish" for item in self.hands)
        if FIRST_SEAT <= action < NUM_ACTIONS:
            g, t = divmod(action - FIRST_SEAT, NUM_TABLES)
            table = self.tables[t]
            return (
                g < len(self.queue)
                and table.status == FREE
                and self.queue[g].size <= table.capacity
            )
        return False

    def action_mask(self) -> list[bool]:
        """``is_legal`` of every action (docs/rules.md §7)."""
        return [self.is_legal(a) for a in range(NUM_ACTIONS)]

    def expert_action(self) -> int:
        """The reference heuristic (docs/rules.md §8): the first action whose shaped one-step
        score change is largest, if positive, else 0."""
        best_action, best_gain = 0, 0
        for action in range(NUM_ACTIONS):
            # An illegal action only lets time pass, like action 0 before it: it cannot be first.
            if action != WAIT and not self.is_legal(action):
                continue
            future = self.copy()
            future._apply(action, shaped=True)
            future._advance()
            gain = future.score - self.score
            if action == WAIT or gain > best_gain:
                best_action, best_gain = action, gain
        return best_action if best_gain > 0 else WAIT

    def observation(self) -> list[int]:
        """The 40 numbers of docs/rules.md §6."""
        obs = []
        for table in self.tables:
            level = table.group.patience // 200 if table.group is not None else -1
            obs += (table.status, table.capacity, level)
        food = [0] * NUM_TABLES
        for t in self.counters:
            if t:
                food[t - 1] = 1
        obs += food
        for group in self.queue:
            obs += (group.patience // 200, group.size)
        obs += [0, 0] * (QUEUE_CAPACITY - len(self.queue))
        for item in self.hands:
            obs.append(_ITEM_OFFSET[item.kind] + item.table)
        obs += [0] * (HAND_CAPACITY - len(self.hands))
        return obs

    def _apply(self, action: int, shaped: bool) -> None:
        """Applies an action (docs/rules.md §4.1); ``shaped`` adds the expert's shaping."""
        if not self.is_legal(action):
            return
        if action == WAIT:
            return
        if 1 <= action <= 6:
            self._go_to(action, shaped)
        elif action == HAND_IN_ORDERS:
            for item in self.hands:
                if item.kind == "order":
                    self.score += 10
                    self.orders.append(Order(item.table, self.now))
            self.hands = [item for item in self.hands if item.kind != "order"]
            self.score += 10
        elif FIRST_PICK_UP <= action < DROP_DISHES:
            t = action - FIRST_PICK_UP + 1
            self.score += 10
            self.counters[self.counters.index(t)] = 0
            self.hands.append(Item("food", t))
            group = self.tables[t - 1].group
            if shaped and group is not None:
                self.score += _shaping(group.patience, 10)
        elif action == DROP_DISHES:
            dishes = sum(1 for item in self.hands if item.kind == "dish")
            self.score += 10 * dishes
            self.hands = [item for item in self.hands if item.kind != "dish"]
            self.score += 10
        else:
            g, t = divmod(action - FIRST_SEAT, NUM_TABLES)
            group = self.queue.pop(g)
            table = self.tables[t]
            if shaped and group.size <= 4 and table.capacity == 6:
                self.score -= 100
            self.score += 10
            group.buffer += 100
            if shaped:
                self.score += _shaping(group.patience, 5)
            table.status = READING
            table.group = group
            table.since = self.now

    def _go_to(self, t: int, shaped: bool) -> None:
        """Actions 1..6, whose preconditions hold."""
        table = self.tables[t - 1]
        group = table.group
        bonus = _shaping(group.patience, 10) if shaped and group is not None else 0
        if table.status == READY_TO_ORDER:
            table.status = WAITING_FOR_FOOD
            group.buffer += 100
            self.hands.append(Item("order", t))
            self.score += 20 + bonus
        elif table.status == WAITING_FOR_FOOD:
            table.status = EATING
            group.buffer += 100
            table.since = self.now
            self.hands.remove(Item("food", t))
            self.score += 30 + bonus
        elif table.status == WAITING_FOR_BILL:
            table.status = DISHES
            table.group = None
            self.score += 50 + bonus
        else:
            # DISHES: the hand was free.
            table.status = FREE
            self.hands.append(Item("dish", t))
            self.score += 40

    def _advance(self) -> None:
        """One tick of time (docs/rules.md §5)."""
        config = self.config
        now = self.now

        # 1. The queue loses patience; a group at 0 walks out without a penalty.
        waiting = []
        for group in self.queue:
            if group.decay(config):
                self.lost += 1
            else:
                waiting.append(group)
        self.queue = waiting

        # 2. Seated groups lose patience; at 0 they run away.
        for t, table in enumerate(self.tables, start=1):
            if table.group is not None and table.group.decay(config):
                table.status = FREE
                table.group = None
                table.since = 0
                self._run_away(t)

        # 3. The kitchen.
        pending = []
        for order in self.orders:
            if now - order.placed < config.cooking_ticks:
                pending.append(order)
                continue
            if order.table in self.counters:
                # Quirk: this order and every later one are dropped. (Play never gets here: a
                # table has one order or plate at a time. No recorded trajectory checks it.)
                break
            # Quirk: with no empty slot the food is lost.
            if 0 in self.counters:
                self.counters[self.counters.index(0)] = order.table
        self.orders = pending

        # 4. Reading and eating end.
        for table in self.tables:
            if table.status == READING and now - table.since >= config.reading_ticks:
                table.status = READY_TO_ORDER
            elif table.status == EATING and now - table.since >= config.eating_ticks:
                table.status = WAITING_FOR_BILL

        # 5. Arrivals.
        if now > self.next_arrival and len(self.queue) < QUEUE_CAPACITY:
            self._arrive()

        # 6.
        self.now = now + 1

    def _run_away(self, t: int) -> None:
        """The group of table ``t`` ran away: its items, food and order go too."""
        self.lost += 1
        self.score -= 500
        self.hands = [item for item in self.hands if item.table != t]
        self.counters = [0 if c == t else c for c in self.counters]
        self.orders = [order for order in self.orders if order.table != t]

    def _arrive(self) -> None:
        """The next group of the arrival list joins the queue (which has room)."""
        customer_type, size = self.arrivals[self.arrived % len(self.arrivals)]
        patience = self.config.patience[customer_type - 1]
        self.queue.append(Group(customer_type, size, patience))
        self.arrived += 1
        self.next_arrival = self.now + self.config.arrival_interval


class Game:
    """A restaurant plus the random stream that draws each episode's arrival list.

    ``seed`` starts the stream (like ``random.seed(seed)``); without one, the first reset without
    a seed draws one from system entropy, readable afterwards as ``game.seed``.
    """

    def __init__(self, seed: int | None = None, config: Config | None = None) -> None:
        self.config = config if config is not None else Config()
        self.seed: int | None = None
        self._rng = random.Random()
        if seed is not None:
            self._start_stream(seed)
        self.restaurant: Restaurant | None = None

    def _start_stream(self, seed: int) -> None:
        if seed < 0:
            raise ValueError(f"seed must be a non-negative integer, got {seed}")
        self.seed = seed
        self._rng.seed(seed)

    def reset(self, seed: int | None = None) -> list[int]:
        """Starts an episode (docs/rules.md §3) and returns its first observation. With a seed
        the random stream restarts from it; without one it continues."""
        if seed is not None:
            self._start_stream(seed)
        elif self.seed is None:
            self._start_stream(random.SystemRandom().getrandbits(64))
        rng = self._rng
        # Type before size in each pair (docs/rules.md §2).
        arrivals = [(rng.randint(1, 2), rng.randint(1, 6)) for _ in range(ARRIVALS_PER_EPISODE)]
        self.restaurant = Restaurant(self.config, arrivals)
        return self.restaurant.observation()

    def step(self, action: int) -> tuple[list[int], int, bool]:
        """One step: ``(observation, reward, done)``; ``done`` when the episode terminated (or
        reached the configured time limit). Actions outside 0..56 are refused, as by the server."""
        if self.restaurant is None:
            raise RuntimeError("the game was never reset; call reset")
        if not 0 <= action < NUM_ACTIONS:
            raise ValueError(f"action must be in 0..={NUM_ACTIONS - 1}, got {action}")
        restaurant = self.restaurant
        reward = restaurant.step(action)
        done = restaurant.terminated or restaurant.truncated
        return restaurant.observation(), reward, done

    def _current(self) -> Restaurant:
        if self.restaurant is None:
            raise RuntimeError("the game was never reset; call reset")
        return self.restaurant

    @property
    def score(self) -> int:
        return self._current().score

    @property
    def lost(self) -> int:
        return self._current().lost

    @property
    def tick(self) -> int:
        return self._current().now

    def action_mask(self) -> list[bool]:
        return self._current().action_mask()

    def expert_action(self) -> int:
        return self._current().expert_action()


def random_steps_per_second(steps: int, seed: int = 0) -> float:
    """Steps per second of this simulator under a uniformly random policy (actions drawn in
    0..56, as the reference's random agent draws them), resetting at each episode's end: the
    in-process baseline of ``bench``. The clock covers ``steps`` steps after ``WARMUP_STEPS``
    unmeasured ones; ``seed`` fixes both the episodes and the actions."""
    if steps <= 0:
        raise ValueError(f"steps must be positive, got {steps}")
    game = Game(seed)
    game.reset()
    # The policy's own stream, apart from the game's (a string seed keeps the two unrelated).
    policy = random.Random(f"random policy {seed}")

    def play(n: int) -> None:
        for _ in range(n):
            _, _, done = game.step(policy.randint(0, NUM_ACTIONS - 1))
            if done:
                game.reset()

    play(WARMUP_STEPS)
    start = time.perf_counter()
    play(steps)
    return steps / (time.perf_counter() - start)

"""The ``rgb_array`` render mode: a picture of the restaurant drawn with numpy alone, from the
observation (docs/rules.md section 6) plus the score and lives, so any observation can be drawn,
a dataset's too. The observation says which tables' food is on a counter, not in which slot: the
filled slots are drawn in table order.
"""

from __future__ import annotations

import numpy as np

from .game import NUM_TABLES, OBSERVATION_SIZE, QUEUE_CAPACITY

__all__ = ["STATUS_COLORS", "draw"]

WIDTH, HEIGHT = 400, 260

#: Table colours by status (docs/rules.md section 1).
STATUS_COLORS = np.array(
    [
        (214, 214, 214),  # 0 free and clean
        (120, 170, 230),  # 1 reading the menu
        (245, 215, 70),  # 2 ready to order
        (240, 150, 50),  # 3 waiting for food
        (110, 200, 110),  # 4 eating
        (150, 110, 80),  # 5 left, dishes on the table
        (190, 120, 220),  # 6 waiting for the bill
    ],
    dtype=np.uint8,
)
_FLOOR = (250, 244, 230)
_INK = (40, 40, 40)
_ORDER = (255, 255, 255)
_FOOD = (240, 150, 50)
_DISH = (150, 110, 80)
_HEART = (220, 40, 60)
_SLOT = (200, 190, 170)
# Patience levels 0..4 from red to green.
_PATIENCE = np.array(
    [(220, 40, 40), (235, 120, 40), (230, 200, 50), (150, 210, 60), (60, 180, 70)], np.uint8
)

# Chairs around a table, relative to its cell: two above, two below, then left and right.
_CHAIRS = [(20, 0), (54, 0), (20, 64), (54, 64), (0, 32), (74, 32)]

# A 3x5 pixel font for digits and the few letters the picture uses.
_GLYPHS = {
    "0": "111101101101111",
    "1": "010110010010111",
    "2": "111001111100111",
    "3": "111001111001111",
    "4": "101101111001001",
    "5": "111100111001111",
    "6": "111100111101111",
    "7": "111001010010010",
    "8": "111101111101111",
    "9": "111101111001111",
    "-": "000000111000000",
    " ": "000000000000000",
    "S": "111100111001111",
    "C": "111100100100111",
    "O": "111101101101111",
    "R": "110101110101101",
    "E": "111100111100111",
    "L": "100100100100111",
    "I": "111010010010111",
    "V": "101101101101010",
    "T": "111010010010010",
}


def _rect(img: np.ndarray, x: int, y: int, w: int, h: int, color) -> None:
    img[max(y, 0) : max(y + h, 0), max(x, 0) : max(x + w, 0)] = color


def _frame(img: np.ndarray, x: int, y: int, w: int, h: int, color, t: int = 1) -> None:
    _rect(img, x, y, w, t, color)
    _rect(img, x, y + h - t, w, t, color)
    _rect(img, x, y, t, h, color)
    _rect(img, x + w - t, y, t, h, color)


def _text(img: np.ndarray, x: int, y: int, text: str, color=_INK, scale: int = 2) -> int:
    """Draws ``text`` with its top-left corner at (x, y); returns the x after it."""
    for ch in text.upper():
        bits = np.array([c == "1" for c in _GLYPHS.get(ch, _GLYPHS[" "])]).reshape(5, 3)
        mask = np.kron(bits, np.ones((scale, scale), dtype=bool))
        region = img[y : y + 5 * scale, x : x + 3 * scale]
        region[mask[: region.shape[0], : region.shape[1]]] = color
        x += 4 * scale
    return x


def _item(img: np.ndarray, x: int, y: int, code: int) -> None:
    """A hand slot: 0 empty, t order(t), 6+t food(t), 12+t dish(t)."""
    _rect(img, x, y, 30, 30, _SLOT)
    if code <= 0:
        return
    kind, table = divmod(code - 1, 6)
    color = (_ORDER, _FOOD, _DISH)[min(kind, 2)]
    _rect(img, x + 3, y + 3, 24, 24, color)
    _text(img, x + 12, y + 10, str(table + 1))


def draw(observation: np.ndarray, *, score: int = 0, lost: int = 0, lives: int = 5) -> np.ndarray:
    """The picture of one observation: an ``(HEIGHT, WIDTH, 3)`` ``uint8`` RGB array."""
    obs = np.asarray(observation).astype(np.int64).reshape(-1)
    if obs.shape != (OBSERVATION_SIZE,):
        raise ValueError(
            f"expected an observation of {OBSERVATION_SIZE} numbers, got shape "
            f"{np.shape(observation)}"
        )
    img = np.empty((HEIGHT, WIDTH, 3), dtype=np.uint8)
    img[:] = _FLOOR

    # Score and lives.
    _text(img, 8, 8, f"SCORE {score}")
    x = _text(img, 236, 8, "LIVES ")
    for i in range(max(lives, 0)):
        _rect(img, x + 14 * i, 8, 10, 10, _HEART if i < lives - lost else _SLOT)

    # Queue: group 1 (oldest) on top; heads for the size, a bar for the patience.
    for g in range(QUEUE_CAPACITY):
        level, size = obs[24 + 2 * g], obs[25 + 2 * g]
        y = 48 + 28 * g
        _rect(img, 8, y, 66, 24, (235, 228, 212))
        if size > 0:
            for k in range(size):
                _rect(img, 12 + 10 * k, y + 3, 8, 8, _INK)
            _rect(img, 12, y + 15, 12 * (level + 1), 5, _PATIENCE[min(max(level, 0), 4)])

    # Tables 1..6 in two rows of three.
    for t in range(NUM_TABLES):
        status, capacity, level = obs[3 * t], obs[3 * t + 1], obs[3 * t + 2]
        x, y = 88 + 92 * (t % 3), 36 + 92 * (t // 3)
        color = STATUS_COLORS[min(max(status, 0), 6)]
        _rect(img, x + 10, y + 10, 62, 52, color)
        _frame(img, x + 10, y + 10, 62, 52, _INK)
        _text(img, x + 14, y + 14, str(t + 1))
        for cx, cy in _CHAIRS[: max(capacity, 0)]:
            _rect(img, x + cx, y + cy, 8, 8, _INK)
        if level >= 0:  # a seated group: its patience bar
            _rect(img, x + 16, y + 48, 10 * (level + 1), 8, _PATIENCE[min(level, 4)])
        if obs[18 + t]:  # its food waits on a counter
            _rect(img, x + 58, y + 14, 10, 10, _FOOD)

    # Counters: 5 slots; the ready food, in table order.
    ready = [t for t in range(NUM_TABLES) if obs[18 + t]]
    for s in range(5):
        y = 48 + 34 * s
        _rect(img, 364, y, 30, 30, _SLOT)
        if s < len(ready):
            _rect(img, 367, y + 3, 24, 24, _FOOD)
            _text(img, 376, y + 10, str(ready[s] + 1))

    # Hands.
    _item(img, 180, 222, int(obs[38]))
    _item(img, 216, 222, int(obs[39]))
    return img

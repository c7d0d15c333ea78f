// The restaurant drawn on a 400 x 260 canvas from one observation, pixel for pixel the picture of
// the Python client's rgb_array render mode (client-py/dinerdash/render.py): same colours, same
// places, same 3x5 pixel font. Everything comes from the 40-number observation plus the score,
// the groups lost and the lives.
"use strict";

const Board = (() => {
  const WIDTH = 400;
  const HEIGHT = 260;
  // Table colours by status (docs/rules.md section 1).
  const STATUS_COLORS = [
    [214, 214, 214], // 0 free and clean
    [120, 170, 230], // 1 reading the menu
    [245, 215, 70], // 2 ready to order
    [240, 150, 50], // 3 waiting for food
    [110, 200, 110], // 4 eating
    [150, 110, 80], // 5 left, dishes on the table
    [190, 120, 220], // 6 waiting for the bill
  ];
  const STATUS_NAMES = [
    "free",
    "reading the menu",
    "ready to order",
    "waiting for food",
    "eating",
    "dishes to clear",
    "waiting for the bill",
  ];
  const FLOOR = [250, 244, 230];
  const INK = [40, 40, 40];
  const ORDER = [255, 255, 255];
  const FOOD = [240, 150, 50];
  const DISH = [150, 110, 80];
  const HEART = [220, 40, 60];
  const SLOT = [200, 190, 170];
  const QUEUE_SLOT = [235, 228, 212];
  // Patience levels 0..4 from red to green.
  const PATIENCE = [
    [220, 40, 40],
    [235, 120, 40],
    [230, 200, 50],
    [150, 210, 60],
    [60, 180, 70],
  ];
  // Chairs around a table, relative to its cell: two above, two below, then left and right.
  const CHAIRS = [
    [20, 0],
    [54, 0],
    [20, 64],
    [54, 64],
    [0, 32],
    [74, 32],
  ];
  const GLYPHS = {
    0: "111101101101111",
    1: "010110010010111",
    2: "111001111100111",
    3: "111001111001111",
    4: "101101111001001",
    5: "111100111001111",
    6: "111100111101111",
    7: "111001010010010",
    8: "111101111101111",
    9: "111101111001111",
    "-": "000000111000000",
    " ": "000000000000000",
    S: "111100111001111",
    C: "111100100100111",
    O: "111101101101111",
    R: "110101110101101",
    E: "111100111100111",
    L: "100100100100111",
    I: "111010010010111",
    V: "101101101101010",
    T: "111010010010010",
  };

  const clamp = (v, lo, hi) => Math.min(Math.max(v, lo), hi);

  function painter(ctx) {
    function rect(x, y, w, h, color) {
      // As numpy slicing img[max(y,0):max(y+h,0), max(x,0):max(x+w,0)]: clipped to the picture.
      const x0 = clamp(x, 0, WIDTH);
      const y0 = clamp(y, 0, HEIGHT);
      const x1 = clamp(x + w, 0, WIDTH);
      const y1 = clamp(y + h, 0, HEIGHT);
      if (x1 <= x0 || y1 <= y0) return;
      ctx.fillStyle = `rgb(${color[0]},${color[1]},${color[2]})`;
      ctx.fillRect(x0, y0, x1 - x0, y1 - y0);
    }
    function frame(x, y, w, h, color) {
      rect(x, y, w, 1, color);
      rect(x, y + h - 1, w, 1, color);
      rect(x, y, 1, h, color);
      rect(x + w - 1, y, 1, h, color);
    }
    // Draws text with its top-left corner at (x, y); returns the x after it.
    function text(x, y, str, color = INK, scale = 2) {
      for (const ch of String(str).toUpperCase()) {
        const bits = GLYPHS[ch] || GLYPHS[" "];
        for (let r = 0; r < 5; r++) {
          for (let c = 0; c < 3; c++) {
            if (bits[3 * r + c] === "1") rect(x + c * scale, y + r * scale, scale, scale, color);
          }
        }
        x += 4 * scale;
      }
      return x;
    }
    // A hand slot: 0 empty, t order(t), 6+t food(t), 12+t dish(t).
    function item(x, y, code) {
      rect(x, y, 30, 30, SLOT);
      if (code <= 0) return;
      const kind = Math.floor((code - 1) / 6);
      const table = (code - 1) % 6;
      rect(x + 3, y + 3, 24, 24, [ORDER, FOOD, DISH][Math.min(kind, 2)]);
      text(x + 12, y + 10, String(table + 1));
    }
    return { rect, frame, text, item };
  }

  // Draws observation `obs` (40 numbers) with its score, groups lost and lives.
  function draw(ctx, obs, score = 0, lost = 0, lives = 5) {
    const { rect, frame, text, item } = painter(ctx);
    rect(0, 0, WIDTH, HEIGHT, FLOOR);

    // Score and lives.
    text(8, 8, `SCORE ${score}`);
    const x = text(236, 8, "LIVES ");
    for (let i = 0; i < Math.max(lives, 0); i++) {
      rect(x + 14 * i, 8, 10, 10, i < lives - lost ? HEART : SLOT);
    }

    // Queue: group 1 (oldest) on top; heads for the size, a bar for the patience.
    for (let g = 0; g < 7; g++) {
      const level = obs[24 + 2 * g];
      const size = obs[25 + 2 * g];
      const y = 48 + 28 * g;
      rect(8, y, 66, 24, QUEUE_SLOT);
      if (size > 0) {
        for (let k = 0; k < size; k++) rect(12 + 10 * k, y + 3, 8, 8, INK);
        rect(12, y + 15, 12 * (level + 1), 5, PATIENCE[clamp(level, 0, 4)]);
      }
    }

    // Tables 1..6 in two rows of three.
    for (let t = 0; t < 6; t++) {
      const [status, capacity, level] = [obs[3 * t], obs[3 * t + 1], obs[3 * t + 2]];
      const x = 88 + 92 * (t % 3);
      const y = 36 + 92 * Math.floor(t / 3);
      rect(x + 10, y + 10, 62, 52, STATUS_COLORS[clamp(status, 0, 6)]);
      frame(x + 10, y + 10, 62, 52, INK);
      text(x + 14, y + 14, String(t + 1));
      for (const [cx, cy] of CHAIRS.slice(0, Math.max(capacity, 0))) rect(x + cx, y + cy, 8, 8, INK);
      if (level >= 0) rect(x + 16, y + 48, 10 * (level + 1), 8, PATIENCE[Math.min(level, 4)]);
      if (obs[18 + t]) rect(x + 58, y + 14, 10, 10, FOOD);
    }

    // Counters: 5 slots; the ready food, in table order.
    const ready = [];
    for (let t = 0; t < 6; t++) if (obs[18 + t]) ready.push(t);
    for (let s = 0; s < 5; s++) {
      const y = 48 + 34 * s;
      rect(364, y, 30, 30, SLOT);
      if (s < ready.length) {
        rect(367, y + 3, 24, 24, FOOD);
        text(376, y + 10, String(ready[s] + 1));
      }
    }

    // Hands.
    item(180, 222, obs[38]);
    item(216, 222, obs[39]);
  }

  // Where the middle of table t (0-based) is drawn, for pointing at it.
  function tableCentre(t) {
    return [88 + 92 * (t % 3) + 41, 36 + 92 * Math.floor(t / 3) + 36];
  }

  // The name of action a (docs/rules.md section 4.1).
  function actionName(a) {
    if (a === 0) return "wait";
    if (a <= 6) return `go to table ${a}`;
    if (a === 7) return "hand the orders to the kitchen";
    if (a <= 13) return `pick up the food of table ${a - 7}`;
    if (a === 14) return "drop the dishes";
    const g = Math.floor((a - 15) / 6) + 1;
    const t = ((a - 15) % 6) + 1;
    return `seat group ${g} at table ${t}`;
  }

  return {
    WIDTH,
    HEIGHT,
    STATUS_COLORS,
    STATUS_NAMES,
    PATIENCE,
    draw,
    tableCentre,
    actionName,
  };
})();

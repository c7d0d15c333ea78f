// The play page: a game of one's own, drawn with the watch page's Board, every action a target
// (`data-action="<id>"`, hidden and disabled when the mask says it is illegal), keyboard
// shortcuts, hints, turn-based or real-time play, and the recording's download.
//
// `/play?seed=N&lives=3...` starts a game (seed and the GameConfig fields go to the server; `mode`
// and `rate` are the page's); the address then becomes `/play/{id}`, which a reload resumes.
// `/play/replay` (an uploaded recording) or `/play/replay?from={id}` (a game of the token's)
// replays a recording: a new game of its seed and config, stepped with its actions one by one,
// the recorded action outlined beside the hints.
"use strict";

(() => {
  const $ = (name) => document.getElementById(name);
  const canvas = $("board");
  const ctx = canvas.getContext("2d");
  const game = $("game");
  const params = new URLSearchParams(location.search);
  const CONFIG_FIELDS = [
    "arrival_interval",
    "patience_type1",
    "patience_type2",
    "decay_type1",
    "decay_type2",
    "reading_ticks",
    "cooking_ticks",
    "eating_ticks",
    "lives",
    "time_limit",
  ];
  const SCALE = 2;

  let state = null;
  let busy = false; // one request in flight at a time, so actions keep their order
  let actedSinceTick = false; // real time: the player acted during this period
  let timer = null;

  // ---- the targets ------------------------------------------------------------------------
  const targets = new Map();
  function target(action, parent, label, box) {
    const b = document.createElement("button");
    b.type = "button";
    b.dataset.action = String(action);
    b.className = box ? "target on-board" : "target";
    b.title = `${action}: ${Board.actionName(action)}`;
    b.textContent = label;
    if (box) {
      const [x, y, w, h] = box;
      Object.assign(b.style, {
        left: `${x * SCALE}px`,
        top: `${y * SCALE}px`,
        width: `${w * SCALE}px`,
        height: `${h * SCALE}px`,
      });
    }
    b.hidden = true;
    b.disabled = true;
    b.addEventListener("click", () => act(action));
    parent.appendChild(b);
    targets.set(action, b);
  }
  const layer = $("targets");
  for (let t = 0; t < 6; t++) {
    const x = 88 + 92 * (t % 3);
    const y = 36 + 92 * Math.floor(t / 3);
    target(t + 1, layer, "", [x + 10, y + 22, 62, 40]);
    target(8 + t, layer, "food", [x + 10, y + 10, 62, 12]);
  }
  target(0, layer, "wait", [96, 224, 70, 26]);
  target(14, layer, "dishes", [256, 224, 66, 26]);
  target(7, layer, "kitchen", [330, 224, 64, 26]);
  // Seating: a row of six per queue place, beside the board at the group's height.
  const seating = $("seating");
  for (let g = 0; g < 7; g++) {
    const row = document.createElement("div");
    row.className = "seat-row";
    row.style.top = `${(48 + 28 * g) * SCALE}px`;
    for (let t = 0; t < 6; t++) target(15 + 6 * g + t, row, `→${t + 1}`, null);
    seating.appendChild(row);
  }

  // ---- showing a state --------------------------------------------------------------------
  function show(s) {
    state = s;
    game.dataset.sessionId = s.session_id;
    game.dataset.tick = String(s.tick);
    game.dataset.score = String(s.score);
    game.dataset.finished = String(s.finished);
    $("session").textContent = s.session_id.slice(0, 8);
    $("session").title = s.session_id;
    $("seed").textContent = String(s.seed);
    document.title = `play ${s.session_id.slice(0, 8)} · DinerDash`;
    if (s.obs.length) Board.draw(ctx, s.obs, s.score, s.lost, s.lives);
    $("score").textContent = Live.fmt(s.score);
    $("lives").textContent = `${Math.max(s.lives - s.lost, 0)} of ${s.lives}`;
    $("tick").textContent = Live.fmt(s.tick);
    const over = $("over");
    over.hidden = !(s.finished || s.ended);
    over.textContent = s.ended
      ? "This game's session has ended (idle too long); its recording is kept."
      : s.terminated
        ? `Game over: ${s.lost} groups lost. Score ${s.score}.`
        : `Time is up. Score ${s.score}.`;
    const hint = new Set();
    if ($("hint-expert").checked && s.expert.reference !== null) hint.add(s.expert.reference);
    if ($("hint-planner").checked && s.expert.planner !== null) hint.add(s.expert.planner);
    const recorded = replayNext();
    for (const [action, b] of targets) {
      const legal = !s.ended && !s.finished && s.mask[action];
      b.hidden = !legal;
      b.disabled = !legal;
      b.classList.toggle("hint", legal && hint.has(action));
      b.classList.toggle("recorded", legal && action === recorded);
    }
    showReplay();
    const said = [];
    if ($("hint-expert").checked && s.expert.reference !== null) {
      said.push(`expert: ${s.expert.reference} ${Board.actionName(s.expert.reference)}`);
    }
    if ($("hint-planner").checked && s.expert.planner !== null) {
      said.push(`planner: ${s.expert.planner} ${Board.actionName(s.expert.planner)}`);
    }
    $("hints").textContent = said.length ? said.join(" · ") : "–";
    window.lastState = s;
    if (s.finished || s.ended) stopClock();
  }

  function problem(text) {
    const p = $("problem");
    p.textContent = text;
    p.hidden = !text;
  }

  // ---- talking to the server --------------------------------------------------------------
  async function call(method, url, body) {
    const init = { method, headers: Live.headers(), cache: "no-store" };
    if (body !== undefined) {
      init.headers["Content-Type"] = "application/json";
      init.body = JSON.stringify(body);
    }
    const response = await fetch(url, init);
    if (response.status === 401) {
      Live.setStatus("token needed", "down");
      return new Promise((resolve) => {
        Live.askToken("This server asks for a token.", () => resolve(call(method, url, body)));
      });
    }
    const json = await response.json().catch(() => ({}));
    return { status: response.status, json };
  }

  async function act(action, fromClock = false) {
    if (busy || !state || state.finished || state.ended) return;
    if (!fromClock) actedSinceTick = true;
    if (replay && !fromClock && replay.left === undefined && action !== replayNext()) {
      replay.left = state.tick;
    }
    busy = true;
    try {
      const r = await call("POST", `/api/play/${state.session_id}/act`, {
        action,
        tick: state.tick,
      });
      if (r.status === 200) {
        show(r.json);
        $("last").textContent = `tick ${r.json.tick - 1} · ${action}: ${Board.actionName(action)} · reward ${r.json.last_reward}`;
        problem("");
        Live.setStatus("playing", "live");
      } else if (r.status === 409) {
        await refresh();
      } else {
        problem(`The server refused (${r.status}): ${r.json.error || ""}`);
      }
    } catch (e) {
      problem(`The server is unreachable: ${e}`);
    } finally {
      busy = false;
    }
  }

  async function refresh() {
    const r = await call("GET", `/api/play/${state.session_id}`);
    if (r.status === 200) show(r.json);
  }

  // ---- real time ---------------------------------------------------------------------------
  function stopClock() {
    if (timer !== null) clearInterval(timer);
    timer = null;
  }
  function startClock() {
    stopClock();
    if ($("mode").value !== "realtime") return;
    const rate = Math.min(Math.max(parseFloat($("rate").value) || 2, 0.5), 20);
    timer = setInterval(() => {
      if (actedSinceTick) {
        actedSinceTick = false;
        return;
      }
      act(0, true);
    }, 1000 / rate);
  }
  function keepModeInAddress() {
    const q = new URLSearchParams();
    if ($("mode").value === "realtime") {
      q.set("mode", "realtime");
      q.set("rate", $("rate").value);
    }
    const path = state ? `/play/${state.session_id}` : location.pathname;
    history.replaceState(null, "", `${path}${q.toString() ? `?${q}` : ""}`);
  }
  $("mode").value = params.get("mode") === "realtime" ? "realtime" : "turns";
  if (params.get("rate")) $("rate").value = params.get("rate");
  for (const el of [$("mode"), $("rate")]) {
    el.addEventListener("change", () => {
      keepModeInAddress();
      startClock();
    });
  }
  for (const el of [$("hint-expert"), $("hint-planner")]) {
    el.addEventListener("change", () => state && show(state));
  }

  // ---- keys ----------------------------------------------------------------------------------
  let pending = ""; // "f", "s" or "s<g>": the start of a longer shortcut
  document.addEventListener("keydown", (e) => {
    if (e.target instanceof HTMLInputElement || e.target instanceof HTMLSelectElement) return;
    if (e.ctrlKey || e.metaKey || e.altKey) return;
    const k = e.key.toLowerCase();
    const digit = /^[1-7]$/.test(k) ? parseInt(k, 10) : null;
    let action = null;
    if (pending === "f" && digit !== null && digit <= 6) action = 7 + digit;
    else if (pending === "s" && digit !== null) {
      pending = `s${digit}`;
      return;
    } else if (pending.startsWith("s") && pending.length === 2 && digit !== null && digit <= 6) {
      action = 15 + 6 * (parseInt(pending[1], 10) - 1) + (digit - 1);
    } else if (k === " " || k === "0" || k === "w") action = 0;
    else if (digit !== null && digit <= 6) action = digit;
    else if (k === "k") action = 7;
    else if (k === "d") action = 14;
    else if (k === "f" || k === "s") {
      pending = k;
      return;
    } else if (k === "h") {
      const on = !$("hint-expert").checked;
      $("hint-expert").checked = on;
      $("hint-planner").checked = on;
      if (state) show(state);
    }
    pending = "";
    if (action === null) return;
    e.preventDefault();
    const b = targets.get(action);
    if (b && !b.disabled) act(action);
  });

  // ---- the recording ---------------------------------------------------------------------
  $("download").addEventListener("click", async (e) => {
    e.preventDefault();
    if (!state) return;
    const r = await call("GET", `/api/play/${state.session_id}/recording`);
    if (r.status !== 200) {
      problem(`The server refused the recording (${r.status}): ${r.json.error || ""}`);
      return;
    }
    const blob = new Blob([JSON.stringify(r.json)], { type: "application/json" });
    const a = document.createElement("a");
    a.href = URL.createObjectURL(blob);
    a.download = `dinerdash-play-seed${r.json.seed}-${state.session_id.slice(0, 8)}.json`;
    document.body.appendChild(a);
    a.click();
    a.remove();
    setTimeout(() => URL.revokeObjectURL(a.href), 10000);
  });

  // ---- starting or resuming ------------------------------------------------------------------
  // ---- replaying a recording ---------------------------------------------------------------
  let replay = null; // {actions, score, steps}: the recording being replayed
  let replayTimer = null;
  function replayNext() {
    if (!replay || !state || state.steps >= replay.actions.length) return null;
    return replay.actions[state.steps];
  }
  function showReplay() {
    if (!replay) return;
    const next = replayNext();
    const off = replay.left !== undefined;
    $("replay-step").disabled = next === null || off;
    $("replay-play").disabled = next === null || off;
    $("replay-at").textContent = off
      ? `You left the recording at tick ${replay.left}: the rest is yours.`
      : next === null
        ? `The recording's ${replay.actions.length} actions are played: score ${state.score}, the recording's ${replay.score}.`
        : `recorded action ${state.steps + 1} of ${replay.actions.length}: ${next} ${Board.actionName(next)}`;
    if (next === null || off) stopReplay();
  }
  function stopReplay() {
    if (replayTimer !== null) clearInterval(replayTimer);
    replayTimer = null;
    $("replay-play").textContent = "play";
  }
  async function stepReplay() {
    const next = replayNext();
    if (next !== null && !busy) await act(next, true);
  }
  $("replay-step").addEventListener("click", stepReplay);
  $("replay-play").addEventListener("click", () => {
    if (replayTimer !== null) return stopReplay();
    const rate = Math.min(Math.max(parseFloat($("rate").value) || 2, 0.5), 20);
    replayTimer = setInterval(stepReplay, 1000 / rate);
    $("replay-play").textContent = "pause";
  });
  async function startReplay(recording) {
    if (!recording || recording.format !== "dinerdash-play/1" || !Array.isArray(recording.actions)) {
      problem("That is not a recording of this page (format dinerdash-play/1).");
      return;
    }
    const q = new URLSearchParams();
    q.set("seed", String(recording.seed));
    for (const [key, value] of Object.entries(recording.config || {})) {
      if (CONFIG_FIELDS.includes(key) && value !== null) q.set(key, String(value));
    }
    const r = await call("POST", `/api/play?${q}`);
    if (r.status !== 200) {
      problem(`The server refused the replay (${r.status}): ${r.json.error || ""}`);
      return;
    }
    if (r.json.ruleset !== recording.ruleset) {
      problem(`The recording is of ruleset ${recording.ruleset}, this server plays ${r.json.ruleset}.`);
    } else {
      problem("");
    }
    replay = { actions: recording.actions, score: recording.score };
    show(r.json);
    Live.setStatus("replaying", "live");
  }
  $("replay-file").addEventListener("change", async (e) => {
    const file = e.target.files[0];
    if (!file) return;
    let recording = null;
    try {
      recording = JSON.parse(await file.text());
    } catch (err) {
      problem(`That file is not JSON: ${err}`);
      return;
    }
    await startReplay(recording);
  });

  async function begin() {
    const id = decodeURIComponent(location.pathname.split("/")[2] || "");
    let r;
    if (id === "replay") {
      $("replay").hidden = false;
      $("mode").disabled = true;
      const from = params.get("from");
      if (from) {
        const rec = await call("GET", `/api/play/${encodeURIComponent(from)}/recording`);
        if (rec.status !== 200) {
          problem(`There is no such game for this token (${rec.status}).`);
          return;
        }
        await startReplay(rec.json);
      }
      return;
    }
    if (id) {
      r = await call("GET", `/api/play/${encodeURIComponent(id)}`);
    } else {
      const q = new URLSearchParams();
      for (const [key, value] of params) {
        if (key === "seed" || CONFIG_FIELDS.includes(key)) q.set(key, value);
      }
      r = await call("POST", `/api/play${q.toString() ? `?${q}` : ""}`);
    }
    if (r.status !== 200) {
      Live.setStatus("refused", "down");
      problem(
        r.status === 404
          ? "There is no such game for this token: the ID is wrong, it was dropped for newer games, or it belongs to another tenant."
          : `The server refused (${r.status}): ${r.json.error || ""}`,
      );
      return;
    }
    show(r.json);
    Live.setStatus("playing", "live");
    keepModeInAddress();
    startClock();
  }
  begin().catch((e) => problem(`The server is unreachable: ${e}`));
})();

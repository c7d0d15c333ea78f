// The watch page: environment K of a session drawn live from /api/watch/{id}/events?env=K, with
// the facts beside it (score, lives, tick, episodes), the expert's choice and the last actions.
"use strict";

(() => {
  const id = decodeURIComponent(location.pathname.split("/")[2] || "");
  const env = Math.max(0, parseInt(new URLSearchParams(location.search).get("env") || "0", 10) || 0);
  const canvas = document.getElementById("board");
  const ctx = canvas.getContext("2d");
  const $ = (name) => document.getElementById(name);

  $("session").textContent = id.slice(0, 8);
  $("session").title = id;
  document.title = `${id.slice(0, 8)} · env ${env} · DinerDash`;

  // The colour legend of the tables.
  Board.STATUS_NAMES.forEach((name, status) => {
    const li = document.createElement("li");
    const swatch = document.createElement("span");
    swatch.className = "swatch";
    const [r, g, b] = Board.STATUS_COLORS[status];
    swatch.style.background = `rgb(${r},${g},${b})`;
    li.append(swatch, name);
    $("legend").appendChild(li);
  });

  let envsListed = 0;
  function listEnvs(n) {
    if (n === envsListed) return;
    envsListed = n;
    const select = $("env");
    select.replaceChildren();
    for (let k = 0; k < Math.min(n, 1024); k++) {
      const option = document.createElement("option");
      option.value = k;
      option.textContent = k;
      option.selected = k === env;
      select.appendChild(option);
    }
    $("num-envs").textContent = `of ${n}`;
  }
  $("env").addEventListener("change", (e) => {
    location.search = `?env=${e.target.value}`;
  });

  function show(f) {
    listEnvs(f.num_envs);
    $("waiting").hidden = f.started;
    canvas.dataset.seq = f.seq;
    canvas.dataset.tick = f.tick;
    canvas.dataset.started = f.started;
    if (f.started) {
      Board.draw(ctx, f.obs, f.score, f.lost, f.lives);
    }
    const over = $("over");
    over.hidden = !(f.terminated || f.truncated);
    over.textContent = f.terminated
      ? `Episode over: ${f.lost} groups lost. Waiting for the next reset.`
      : "Episode truncated. Waiting for the next reset.";
    $("score").textContent = Live.fmt(f.score);
    $("lives").textContent = f.started ? `${Math.max(f.lives - f.lost, 0)} of ${f.lives}` : "–";
    $("tick").textContent = Live.fmt(f.tick);
    $("episodes").textContent = Live.fmt(f.episodes);
    $("recent").textContent = Live.fmt(f.recent_mean, 1);
    $("expert").textContent = f.expert
      ? `${f.expert.action}: ${Board.actionName(f.expert.action)} (${f.expert.by})`
      : "–";
    const moves = $("moves");
    moves.replaceChildren();
    for (const m of f.moves) {
      const li = document.createElement("li");
      const what = document.createElement("span");
      const reward = document.createElement("span");
      reward.className = m.reward > 0 ? "reward up" : m.reward < 0 ? "reward down" : "reward";
      reward.textContent = m.reward > 0 ? `+${m.reward}` : `${m.reward}`;
      if (m.reset && m.tick === 0 && m.action === 0) {
        what.textContent = `tick ${m.tick} · reset: a new episode`;
      } else {
        what.textContent = `tick ${m.tick} · ${m.action}: ${Board.actionName(m.action)}${m.reset ? " (then reset)" : ""}`;
      }
      li.append(what, reward);
      moves.appendChild(li);
    }
    window.lastFrame = f;
  }

  if (!/^[0-9a-f]{32}$/i.test(id)) {
    $("problem").textContent = "A watch address needs a full 32-digit session ID.";
    $("problem").hidden = false;
    return;
  }
  Live.follow(`/api/watch/${id}/events?env=${env}`, {
    data: show,
    gone() {
      const p = $("problem");
      p.textContent = "The session has ended: it was closed or expired.";
      p.hidden = false;
    },
    problem(status, message) {
      const p = $("problem");
      p.textContent =
        status === 404
          ? "There is no such session for this token: it was closed, it expired, or it belongs to another tenant."
          : `The server refused (${status}): ${message}`;
      p.hidden = false;
    },
  });
})();

// The sessions page: one row per live session the viewer may see, updated in place from the
// /api/sessions/events stream (two updates a second); a click on a row opens its watch page.
"use strict";

(() => {
  const body = document.querySelector("#sessions tbody");
  const COLUMNS = [
    "short",
    "tenant",
    "envs",
    "expert",
    "steps",
    "episodes",
    "recent",
    "rate",
    "idle",
    "watch",
  ];

  function watchUrl(id) {
    return `/watch/${id}?env=0`;
  }

  function rowFor(session) {
    let tr = body.querySelector(`tr[data-id="${session.id}"]`);
    if (tr) return tr;
    tr = document.createElement("tr");
    tr.dataset.id = session.id;
    for (const name of COLUMNS) {
      const td = document.createElement("td");
      td.className = name;
      tr.appendChild(td);
    }
    const link = document.createElement("a");
    link.href = watchUrl(session.id);
    link.className = "id";
    link.title = session.id;
    tr.querySelector(".short").appendChild(link);
    const watch = document.createElement("a");
    watch.href = watchUrl(session.id);
    watch.textContent = "watch ›";
    tr.querySelector(".watch").appendChild(watch);
    tr.addEventListener("click", (e) => {
      if (e.target.tagName !== "A") location.href = watchUrl(session.id);
    });
    body.appendChild(tr);
    return tr;
  }

  function idle(seconds) {
    if (seconds < 1) return "active";
    if (seconds < 120) return `${Math.floor(seconds)} s`;
    return `${Math.floor(seconds / 60)} min`;
  }

  function show(data) {
    const t = data.totals;
    document.getElementById("total-sessions").textContent = Live.fmt(t.sessions);
    document.getElementById("total-envs").textContent = Live.fmt(t.envs);
    document.getElementById("total-rate").textContent = Live.fmt(t.steps_per_s);
    const share = t.memory_budget ? (100 * t.memory_used) / t.memory_budget : 0;
    document.getElementById("total-memory").textContent = `${share.toFixed(share < 10 ? 2 : 1)} %`;
    document.getElementById("total-memory-of").textContent =
      `memory budget used (${Live.bytes(t.memory_used)} of ${Live.bytes(t.memory_budget)})`;

    const seen = new Set();
    data.sessions.forEach((s, i) => {
      seen.add(s.id);
      const tr = rowFor(s);
      if (body.children[i] !== tr) body.insertBefore(tr, body.children[i] || null);
      const cell = (name) => tr.querySelector(`.${name}`);
      cell("short").firstChild.textContent = s.short;
      cell("tenant").textContent = s.tenant;
      cell("envs").textContent = Live.fmt(s.envs);
      cell("expert").textContent = s.expert;
      cell("steps").textContent = Live.fmt(s.steps);
      cell("steps").dataset.value = s.steps;
      cell("episodes").textContent = Live.fmt(s.episodes);
      cell("recent").textContent = Live.fmt(s.recent_mean, 1);
      cell("rate").textContent = Live.fmt(s.steps_per_s);
      cell("idle").textContent = idle(s.idle_s);
      tr.classList.toggle("watched", s.viewers > 0);
      tr.title = s.viewers > 0 ? `${s.viewers} watching` : "";
    });
    for (const tr of Array.from(body.children)) {
      if (!seen.has(tr.dataset.id)) tr.remove();
    }
    document.getElementById("empty").hidden = data.sessions.length > 0;
    const more = document.getElementById("more");
    more.hidden = data.visible <= data.sessions.length;
    more.textContent = `Showing the ${data.sessions.length} most recently used of ${Live.fmt(data.visible)} sessions.`;
  }

  Live.follow("/api/sessions/events", {
    data: show,
    gone() {},
    problem(status, message) {
      const p = document.getElementById("problem");
      p.textContent = `The server refused the sessions list (${status}): ${message}`;
      p.hidden = false;
    },
  });
})();

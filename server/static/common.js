// What both pages share: the token (asked for when the server needs one, kept for this tab
// only), and reading a server-sent event stream with fetch, which, unlike EventSource, can send
// the Authorization header.
"use strict";

const Live = (() => {
  const TOKEN_KEY = "dinerdash-token";
  const sleep = (ms) => new Promise((resolve) => setTimeout(resolve, ms));

  function token() {
    return sessionStorage.getItem(TOKEN_KEY) || "";
  }

  function setStatus(text, kind) {
    const el = document.getElementById("status");
    if (!el) return;
    el.textContent = text;
    el.dataset.kind = kind;
  }

  // Shows the token form with `message`; `retry` runs once a token is entered.
  function askToken(message, retry) {
    const form = document.getElementById("token-form");
    const input = document.getElementById("token-input");
    document.getElementById("token-message").textContent = message;
    form.hidden = false;
    input.focus();
    form.onsubmit = (e) => {
      e.preventDefault();
      sessionStorage.setItem(TOKEN_KEY, input.value.trim());
      input.value = "";
      form.hidden = true;
      retry();
    };
  }

  // Follows the event stream at `url`: on.data(object) for each event, on.gone() when the
  // server says the thing watched is gone, on.problem(status, message) when it refuses. A lost
  // connection is retried with backoff. Returns {stop()}.
  function follow(url, on) {
    let stopped = false;
    let controller = null;
    async function run() {
      let delay = 500;
      while (!stopped) {
        controller = new AbortController();
        let response;
        try {
          const headers = {};
          if (token()) headers.Authorization = `Bearer ${token()}`;
          response = await fetch(url, { headers, signal: controller.signal, cache: "no-store" });
        } catch (e) {
          if (stopped) return;
          setStatus("server unreachable: retrying", "down");
          await sleep(delay);
          delay = Math.min(2 * delay, 5000);
          continue;
        }
        if (response.status === 401) {
          const had = token() !== "";
          setStatus("token needed", "down");
          askToken(
            had
              ? "That token was refused. Enter a token of this server."
              : "This server asks for a token (the one your trainer sends).",
            () => run(),
          );
          return;
        }
        if (!response.ok) {
          const body = await response.json().catch(() => ({}));
          setStatus("refused", "down");
          on.problem(response.status, body.error || response.statusText);
          return;
        }
        setStatus("live", "live");
        delay = 500;
        const reader = response.body.pipeThrough(new TextDecoderStream()).getReader();
        let buffer = "";
        try {
          for (;;) {
            const { value, done } = await reader.read();
            if (done) break;
            buffer += value;
            let end;
            while ((end = buffer.indexOf("\n\n")) >= 0) {
              const block = buffer.slice(0, end);
              buffer = buffer.slice(end + 2);
              let event = "message";
              let data = "";
              for (const line of block.split("\n")) {
                if (line.startsWith("event: ")) event = line.slice(7);
                else if (line.startsWith("data: ")) data += line.slice(6);
              }
              if (event === "gone") {
                stopped = true;
                setStatus("ended", "down");
                on.gone();
                return;
              }
              if (data) on.data(JSON.parse(data));
            }
          }
        } catch (e) {
          if (stopped) return;
        }
        setStatus("reconnecting", "down");
        await sleep(delay);
      }
    }
    run();
    return {
      stop() {
        stopped = true;
        if (controller) controller.abort();
      },
    };
  }

  const number = new Intl.NumberFormat("en");
  function fmt(value, digits = 0) {
    if (value === null || value === undefined) return "–";
    return number.format(Number(value.toFixed(digits)));
  }

  function bytes(n) {
    const units = ["B", "KiB", "MiB", "GiB", "TiB"];
    let i = 0;
    while (n >= 1024 && i < units.length - 1) {
      n /= 1024;
      i++;
    }
    return `${n.toFixed(i ? 1 : 0)} ${units[i]}`;
  }

  // The headers of a request with the tab's token, if any.
  function headers(extra = {}) {
    const h = { ...extra };
    if (token()) h.Authorization = `Bearer ${token()}`;
    return h;
  }

  return { follow, fmt, bytes, setStatus, headers, askToken };
})();

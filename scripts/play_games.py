#!/usr/bin/env python3
"""Plays games on the server's ``/play`` page in headless Chromium, as a scripted person: each
tick it reads the page's hint (the planner's choice, or the reference expert's) and clicks that
action's ``[data-action]`` target. Saves each game's recording (``GET
/api/play/<id>/recording``) as ``OUT/game-<seed>.json``, and the page's screenshot as
``docs/play.png`` with ``--screenshot``.

The recordings then become demonstrations (docs/play.md)::

    .venv/bin/python scripts/play_games.py --games 5 --seed 100 --time-limit 400 --out plays
    .venv/bin/python -m dinerdash collect --from-play plays/*.json --out demos
    .venv/bin/python -m dinerdash_agents train bc --demos demos/dinerdash_play.npz --out runs/bc-play
"""

from __future__ import annotations

import argparse
import json
import shutil
import sys
import tempfile
import time
import urllib.request
from pathlib import Path

from dinerdash.connection import Connection
from dinerdash.server import LocalServer
from dinerdash.watch import pages_url

REPO = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(REPO / "scripts"))
from web_screenshots import browser


def wait_for(what: str, condition, timeout: float = 30.0):
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        value = condition()
        if value:
            return value
        time.sleep(0.01)
    raise TimeoutError(f"timed out waiting for {what}")


def play(driver, url: str, seed: int, time_limit: int, hint: str) -> str:
    """One game of seed ``seed`` played to its end by clicking the ``hint``'s choices."""
    query = f"seed={seed}" + (f"&time_limit={time_limit}" if time_limit else "")
    driver.get(f"{url}play?{query}")
    game = driver.find_element("id", "game")
    session_id = wait_for("the game", lambda: game.get_attribute("data-session-id"))
    while True:
        state = driver.execute_script("return window.lastState")
        if state["finished"] or state["ended"]:
            return session_id
        action = state["expert"][hint]
        tick = state["tick"]
        driver.find_element("css selector", f'[data-action="{action}"]').click()
        wait_for(
            f"tick {tick + 1}",
            lambda tick=tick: (
                driver.execute_script("return window.lastState.tick") == tick + 1
            ),
        )


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--games", type=int, default=5)
    parser.add_argument("--seed", type=int, default=100, help="seed of the first game")
    parser.add_argument(
        "--time-limit", type=int, default=0, help="GameConfig time_limit"
    )
    parser.add_argument("--hint", choices=["planner", "reference"], default="planner")
    parser.add_argument("--out", type=Path, default=Path("plays"))
    parser.add_argument(
        "--screenshot", type=Path, default=None, help="e.g. docs/play.png"
    )
    parser.add_argument(
        "--server", default=str(REPO / "target" / "release" / "dinerdash-server")
    )
    args = parser.parse_args()

    server = LocalServer(binary=args.server, args=["--http-port", "0"])
    server.start()
    profile = tempfile.mkdtemp(prefix="dinerdash-chromium-")
    driver = None
    try:
        with Connection(server.address) as conn:
            url = pages_url(conn)
        driver = browser(profile)
        driver.set_window_size(1500, 820)
        args.out.mkdir(parents=True, exist_ok=True)
        if args.screenshot is not None:
            driver.get(f"{url}play?seed={args.seed}")
            wait_for(
                "the game", lambda: driver.execute_script("return window.lastState")
            )
            driver.find_element("id", "hint-expert").click()
            driver.find_element("id", "hint-planner").click()
            for _ in range(60):
                state = driver.execute_script("return window.lastState")
                driver.find_element(
                    "css selector", f'[data-action="{state["expert"]["planner"]}"]'
                ).click()
                wait_for(
                    "a tick",
                    lambda t=state["tick"]: (
                        driver.execute_script("return window.lastState.tick") == t + 1
                    ),
                )
            driver.execute_script("window.scrollTo(0, 0)")
            args.screenshot.parent.mkdir(parents=True, exist_ok=True)
            driver.save_screenshot(str(args.screenshot))
            print(args.screenshot)
        for seed in range(args.seed, args.seed + args.games):
            began = time.monotonic()
            session_id = play(driver, url, seed, args.time_limit, args.hint)
            with urllib.request.urlopen(f"{url}api/play/{session_id}/recording") as r:
                recording = json.loads(r.read())
            path = args.out / f"game-{seed}.json"
            path.write_text(json.dumps(recording))
            print(
                f"{path}: {recording['steps']} clicks, score {recording['score']}, "
                f"{time.monotonic() - began:.1f} s",
                flush=True,
            )
    finally:
        if driver is not None:
            driver.quit()
        shutil.rmtree(profile, ignore_errors=True)
        server.stop()
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

#!/usr/bin/env python3
"""Screenshots of the server's web pages for the docs: docs/watch-sessions.png (the live sessions)
and docs/watch-env.png (one environment playing).

Starts ``target/release/dinerdash-server --http-port 0``, three trainers (eight environments
playing the reference expert's choices, four more, and one playing at random), then photographs
both pages in Debian's headless Chromium (``apt-get install chromium chromium-driver``) through
Selenium (the client's ``dev`` extra)::

    .venv/bin/python scripts/web_screenshots.py [--out docs]
"""

from __future__ import annotations

import argparse
import os
import shutil
import tempfile
import threading
import time
from pathlib import Path

import dinerdash  # noqa: F401  (registers the environments)
import gymnasium as gym
import numpy as np
from dinerdash.connection import Connection
from dinerdash.server import LocalServer
from dinerdash.watch import pages_url

REPO = Path(__file__).resolve().parent.parent


def trainer(
    address: str, num_envs: int, expert: bool, pause: float, stop: threading.Event
):
    """Steps a vector env until ``stop``: the expert's choices, or random actions."""
    envs = gym.make_vec(
        "dinerdash:DinerDash-v0", num_envs=num_envs, address=address, expert=expert
    )
    rng = np.random.default_rng(num_envs)
    try:
        _, info = envs.reset(seed=num_envs)
        while not stop.is_set():
            actions = info["expert_action"] if expert else rng.integers(0, 57, num_envs)
            _, _, _, _, info = envs.step(actions)
            time.sleep(pause)
    finally:
        envs.close()


def browser(profile: str):
    from selenium import webdriver
    from selenium.webdriver.chrome.options import Options
    from selenium.webdriver.chrome.service import Service

    os.environ["SE_OFFLINE"] = "true"
    options = Options()
    options.binary_location = shutil.which("chromium")
    for flag in (
        "--headless",
        "--no-sandbox",
        "--disable-gpu",
        "--disable-quic",
        "--no-first-run",
        "--disable-background-networking",
        "--disable-component-update",
        "--disable-sync",
        f"--user-data-dir={profile}",
        "--window-size=1280,860",
        "--hide-scrollbars",
    ):
        options.add_argument(flag)
    service = Service(executable_path=shutil.which("chromedriver"))
    return webdriver.Chrome(service=service, options=options)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, default=REPO / "docs")
    parser.add_argument(
        "--server", default=str(REPO / "target" / "release" / "dinerdash-server")
    )
    args = parser.parse_args()

    server = LocalServer(binary=args.server, args=["--http-port", "0"])
    server.start()
    stop = threading.Event()
    threads = [
        threading.Thread(target=trainer, args=(server.address, n, expert, pause, stop))
        for n, expert, pause in [(8, True, 0.02), (4, True, 0.005), (1, False, 0.01)]
    ]
    profile = tempfile.mkdtemp(prefix="dinerdash-chromium-")
    driver = None
    try:
        for t in threads:
            t.start()
        with Connection(server.address) as conn:
            url = pages_url(conn)
        driver = browser(profile)
        time.sleep(4)  # a few episodes' worth of ticks, and rates to show
        driver.get(url)
        time.sleep(2)
        args.out.mkdir(parents=True, exist_ok=True)
        driver.save_screenshot(str(args.out / "watch-sessions.png"))
        # The first row's session (the oldest: the eight expert environments), environment 3.
        first = driver.find_element("css selector", "tbody tr").get_attribute("data-id")
        driver.get(f"{url}watch/{first}?env=3")
        time.sleep(3)
        driver.save_screenshot(str(args.out / "watch-env.png"))
        print(args.out / "watch-sessions.png")
        print(args.out / "watch-env.png")
    finally:
        stop.set()
        for t in threads:
            t.join(timeout=30)
        if driver is not None:
            driver.quit()
        shutil.rmtree(profile, ignore_errors=True)
        server.stop()
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

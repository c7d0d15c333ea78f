"""The server's web pages in a real browser: Debian's headless Chromium, driven by Selenium
through chromedriver (``apt-get install chromium chromium-driver``; nothing is downloaded).

- the sessions page lists a session a client created, and its tick count rises as it steps;
- the watch page draws the restaurant, pixel for pixel the client's ``rgb_array`` picture, and
  follows the session as the client steps it;
- a wrong token and an unknown session ID are refused.

Set ``DINERDASH_SCREENSHOTS=DIR`` to also save the pages' screenshots there (docs/ holds them).
"""

from __future__ import annotations

import base64
import os
import shutil
import sys
import tempfile
import time
from collections.abc import Iterator
from pathlib import Path

import dinerdash  # noqa: F401  (registers the environments)
import gymnasium as gym
import numpy as np
import pytest
from dinerdash import render
from dinerdash.connection import Connection
from dinerdash.watch import pages_url

CHROMIUM = shutil.which("chromium") or shutil.which("chromium-browser")
CHROMEDRIVER = shutil.which("chromedriver")
pytestmark = pytest.mark.skipif(
    CHROMIUM is None or CHROMEDRIVER is None,
    reason="needs Debian's chromium and chromium-driver: apt-get install -y chromium "
    "chromium-driver",
)
# Longest wait for the page to show something: far above the half-second updates.
PATIENCE = 30.0
SCREENSHOTS = os.environ.get("DINERDASH_SCREENSHOTS")


@pytest.fixture(scope="module")
def browser() -> Iterator:
    try:
        from selenium import webdriver
        from selenium.webdriver.chrome.options import Options
        from selenium.webdriver.chrome.service import Service
    except ImportError:
        pytest.fail("selenium is needed: pip install -e 'client-py[dev]'", pytrace=False)
    # Never let Selenium look for a driver or a browser online.
    os.environ["SE_OFFLINE"] = "true"
    profile = tempfile.mkdtemp(prefix="dinerdash-chromium-")
    options = Options()
    options.binary_location = CHROMIUM
    for flag in (
        "--headless",
        "--no-sandbox",
        "--disable-gpu",
        "--disable-quic",
        "--no-first-run",
        "--disable-background-networking",
        "--disable-component-update",
        "--disable-sync",
        "--disable-dev-shm-usage",
        f"--user-data-dir={profile}",
        "--window-size=1280,900",
    ):
        options.add_argument(flag)
    from selenium.common.exceptions import WebDriverException

    # Starting chromedriver and Chromium failed once in several full runs, before any page was
    # asked for: a second start is tried, and the first failure is printed for the record.
    try:
        driver = webdriver.Chrome(service=Service(executable_path=CHROMEDRIVER), options=options)
    except WebDriverException as e:
        print(f"chromium did not start, trying once more: {e!r}", file=sys.stderr)
        driver = webdriver.Chrome(service=Service(executable_path=CHROMEDRIVER), options=options)
    driver.set_page_load_timeout(PATIENCE)
    try:
        yield driver
    finally:
        driver.quit()
        shutil.rmtree(profile, ignore_errors=True)


def wait_for(what: str, condition, timeout: float = PATIENCE):
    """Polls ``condition()`` until it returns something truthy; fails naming ``what``."""
    deadline = time.monotonic() + timeout
    last = None
    while time.monotonic() < deadline:
        last = condition()
        if last:
            return last
        time.sleep(0.05)
    pytest.fail(f"timed out waiting for {what} (last: {last!r})")


def page_url(server, token: str | None = None) -> str:
    with Connection(server.address, token=token) as conn:
        return pages_url(conn)


def shoot(driver, name: str) -> None:
    if SCREENSHOTS:
        Path(SCREENSHOTS).mkdir(parents=True, exist_ok=True)
        driver.save_screenshot(str(Path(SCREENSHOTS) / name))


def canvas_pixels(driver) -> np.ndarray:
    """The watch page's canvas as an (H, W, 3) uint8 array."""
    data = driver.execute_script(
        """
        const c = document.getElementById("board");
        const d = c.getContext("2d").getImageData(0, 0, c.width, c.height).data;
        let s = "";
        for (let i = 0; i < d.length; i += 8192) {
          s += String.fromCharCode.apply(null, d.subarray(i, i + 8192));
        }
        return [c.width, c.height, btoa(s)];
        """
    )
    width, height, b64 = data
    rgba = np.frombuffer(base64.b64decode(b64), np.uint8).reshape(height, width, 4)
    return rgba[..., :3]


def shown_frame(driver) -> dict:
    return driver.execute_script("return window.lastFrame || null")


def test_sessions_page_lists_a_session_and_follows_its_steps(start_server, browser) -> None:
    from selenium.webdriver.common.by import By

    server = start_server("--http-port", "0")
    url = page_url(server)
    with gym.make("dinerdash:DinerDash-v0", address=server.address, expert=True) as env:
        _, info = env.reset(seed=4)
        session_id = env.unwrapped.session_id
        browser.get(url)
        row = f'tr[data-id="{session_id}"]'
        wait_for("the session's row", lambda: browser.find_elements(By.CSS_SELECTOR, row))
        cell = f"{row} td.steps"

        def steps() -> int:
            value = browser.find_element(By.CSS_SELECTOR, cell).get_attribute("data-value")
            return int(value or 0)

        assert browser.find_element(By.CSS_SELECTOR, f"{row} td.envs").text == "1"
        assert browser.find_element(By.CSS_SELECTOR, f"{row} td.expert").text == "reference"
        assert browser.find_element(By.CSS_SELECTOR, f"{row} td.short").text == session_id[:8]
        before = steps()
        for _ in range(25):
            _, _, terminated, truncated, info = env.step(info["expert_action"])
            assert not (terminated or truncated)
        wait_for("the tick count to rise by 25", lambda: steps() >= before + 25)
        assert steps() == before + 25
        total = browser.find_element(By.ID, "total-sessions").text
        assert total == "1"
        shoot(browser, "sessions.png")

        # A click on the row opens its watch page.
        browser.find_element(By.CSS_SELECTOR, f"{row} td.short a").click()
        wait_for("the watch page", lambda: "/watch/" in browser.current_url)
        assert browser.current_url.endswith(f"/watch/{session_id}?env=0")
        wait_for("the first frame", lambda: shown_frame(browser))


def test_watch_page_draws_the_restaurant_and_follows_the_client(start_server, browser) -> None:
    server = start_server("--http-port", "0")
    envs = gym.make_vec("dinerdash:DinerDash-v0", num_envs=2, address=server.address, expert=True)
    try:
        obs, info = envs.reset(seed=11)
        url = envs.unwrapped.watch_url(1)
        assert url.startswith(page_url(server)) and url.endswith("?env=1")
        browser.get(url)
        frame = wait_for("the first frame", lambda: shown_frame(browser))
        assert frame["started"] and frame["tick"] == 0 and frame["env"] == 1
        assert frame["obs"] == obs[1].tolist()

        def same_picture(frame: dict) -> None:
            expected = render.draw(
                np.array(frame["obs"]),
                score=frame["score"],
                lost=frame["lost"],
                lives=frame["lives"],
            )
            pixels = canvas_pixels(browser)
            assert pixels.shape == expected.shape
            differ = np.argwhere((pixels != expected).any(axis=2))
            assert differ.size == 0, f"{len(differ)} pixels differ from rgb_array: {differ[:5]}"
            # Each table's colour at its middle is its status's.
            for t in range(6):
                x, y = 88 + 92 * (t % 3) + 40, 36 + 92 * (t // 3) + 30
                status = frame["obs"][3 * t]
                assert pixels[y, x].tolist() == render.STATUS_COLORS[status].tolist(), t

        same_picture(frame)
        assert frame["expert"]["action"] == int(info["expert_action"][1])

        # The client steps; the page follows.
        for _ in range(40):
            obs, rewards, _, _, info = envs.step(info["expert_action"])
        frame = wait_for(
            "the page to follow 40 steps",
            lambda: (f := shown_frame(browser)) and f["tick"] == 40 and f,
        )
        assert frame["obs"] == obs[1].tolist()
        assert frame["score"] == int(info["score"][1])
        assert frame["moves"][0]["tick"] == 40
        same_picture(frame)
        shoot(browser, "watch.png")
    finally:
        envs.close()


def test_a_wrong_token_and_an_unknown_session_are_refused(start_server, browser, tmp_path) -> None:
    from selenium.webdriver.common.by import By

    tokens = tmp_path / "tokens"
    token_a, token_b = "team-a-token-aaaa", "team-b-token-bbbb"
    tokens.write_text(f"team-a {token_a}\nteam-b {token_b}\n")
    server = start_server("--http-port", "0", "--auth-tokens-file", str(tokens))
    url = page_url(server, token=token_a)
    with gym.make("dinerdash:DinerDash-v0", address=server.address, token=token_a) as env:
        env.reset(seed=2)
        session_id = env.unwrapped.session_id
        watch = env.unwrapped.watch_url()

        browser.get(url)
        browser.execute_script("sessionStorage.clear()")
        browser.get(url)
        form = browser.find_element(By.ID, "token-form")
        wait_for("the token form", form.is_displayed)

        def enter(token: str) -> None:
            field = browser.find_element(By.ID, "token-input")
            field.clear()
            field.send_keys(token)
            browser.find_element(By.CSS_SELECTOR, "#token-form button").click()

        enter("wrong")
        message = browser.find_element(By.ID, "token-message")
        wait_for("the refusal", lambda: form.is_displayed() and "refused" in message.text)
        assert not browser.find_elements(By.CSS_SELECTOR, "tr[data-id]")
        enter(token_b)  # a token, but another tenant's: its list does not hold the session
        wait_for("team-b's empty list", lambda: browser.find_element(By.ID, "empty").is_displayed())
        assert not browser.find_elements(By.CSS_SELECTOR, "tr[data-id]")

        # The watch page with team-b's token: not found, nothing drawn.
        browser.get(watch)
        problem = browser.find_element(By.ID, "problem")
        wait_for("the refusal of another tenant", problem.is_displayed)
        assert "no such session" in problem.text
        assert shown_frame(browser) is None

        browser.execute_script("sessionStorage.clear()")
        browser.get(url)
        enter(token_a)
        wait_for(
            "team-a's session",
            lambda: browser.find_elements(By.CSS_SELECTOR, f'tr[data-id="{session_id}"]'),
        )
        assert browser.find_element(By.CSS_SELECTOR, "td.tenant").text == "tenant team-a"

        # An unknown session ID: with tokens the page loads for any ID (a browser opening it
        # sends no token, and the page must not tell anyone which IDs exist); the token's feed
        # then refuses it exactly as it refuses another tenant's session.
        browser.get(f"{url}watch/{'0' * 32}?env=0")
        problem = browser.find_element(By.ID, "problem")
        wait_for("the refusal of an unknown ID", problem.is_displayed)
        assert "no such session" in problem.text
        assert shown_frame(browser) is None

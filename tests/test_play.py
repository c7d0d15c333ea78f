"""Playing in the browser (``/play``), recordings, and recordings as demonstrations.

- a scripted player clicks the page's ``[data-action]`` targets for 150 ticks, following the
  reference expert of a twin env of the same seed: the recording holds exactly the clicks and the
  twin's score, and ``collect --from-play`` of it gives the twin's observations, masks and actions;
  an illegal action's target cannot be clicked;
- the real-time mode sends "wait" on its own, no faster than its rate;
- another tenant gets for a game exactly what an unknown ID gets; bad requests are refused;
- a recording that is malformed, of another ruleset, or does not replay to its score is refused,
  naming the step, and nothing is written.

The browser parts use test_watch_browser's Chromium fixture and helpers (Debian's ``chromium``
and ``chromium-driver``; skipped without them).
"""

from __future__ import annotations

import importlib.util
import json
import time
import urllib.error
import urllib.request
from pathlib import Path

import dinerdash  # noqa: F401  (registers the environments)
import gymnasium as gym
import numpy as np
import pytest
from dinerdash.cli import main as dinerdash_main

from tests.test_watch_browser import CHROMEDRIVER, CHROMIUM, browser, page_url, wait_for

__all__ = ["browser"]  # the fixture, used by the tests below

needs_chromium = pytest.mark.skipif(
    CHROMIUM is None or CHROMEDRIVER is None,
    reason="needs Debian's chromium and chromium-driver: apt-get install -y chromium "
    "chromium-driver",
)
TICKS = 150


def call(url: str, method: str = "GET", body: bytes | None = None, token: str | None = None):
    """``(status, JSON body)`` of one request to the web endpoint."""
    request = urllib.request.Request(url, data=body, method=method)
    if token:
        request.add_header("Authorization", f"Bearer {token}")
    try:
        with urllib.request.urlopen(request, timeout=30) as response:
            return response.status, json.loads(response.read())
    except urllib.error.HTTPError as e:
        text = e.read()
        try:
            return e.code, json.loads(text)
        except ValueError:
            return e.code, {"text": text.decode(errors="replace")}


def act(url: str, session_id: str, action: int, tick=None, token=None):
    body = {"action": action} if tick is None else {"action": action, "tick": tick}
    return call(f"{url}api/play/{session_id}/act", "POST", json.dumps(body).encode(), token=token)


def attribute(driver, name: str) -> str:
    return driver.find_element("id", "game").get_attribute(name) or ""


@needs_chromium
def test_a_game_played_on_the_page_is_recorded_and_becomes_demonstrations(
    start_server, browser, tmp_path, monkeypatch
) -> None:
    from selenium.common.exceptions import ElementNotInteractableException
    from selenium.webdriver.common.by import By

    seed = 21
    monkeypatch.setenv("MINARI_DATASETS_PATH", str(tmp_path / "minari"))
    server = start_server("--http-port", "0")
    url = page_url(server)
    twin = gym.make("dinerdash:DinerDash-v0", address=server.address, expert=True)
    try:
        obs, info = twin.reset(seed=seed)
        observations, masks, clicks = [obs], [info["action_mask"]], []
        browser.get(f"{url}play?seed={seed}")
        session_id = wait_for("a game", lambda: attribute(browser, "data-session-id"))
        assert attribute(browser, "data-tick") == "0"
        assert browser.current_url.endswith(f"/play/{session_id}")

        def illegal_cannot_be_clicked() -> None:
            illegal = int(np.flatnonzero(~info["action_mask"])[0])
            target = browser.find_element(By.CSS_SELECTOR, f'[data-action="{illegal}"]')
            assert not target.is_displayed() and not target.is_enabled()
            with pytest.raises(ElementNotInteractableException):
                target.click()
            # Its key does nothing either (the page checks the mask before sending).
            tick = attribute(browser, "data-tick")
            time.sleep(0.2)
            assert attribute(browser, "data-tick") == tick

        illegal_cannot_be_clicked()
        for i in range(TICKS):
            a = int(info["expert_action"])
            target = browser.find_element(By.CSS_SELECTOR, f'[data-action="{a}"]')
            target.click()
            clicks.append(a)
            obs, _, terminated, truncated, info = twin.step(a)
            observations.append(obs)
            masks.append(info["action_mask"])
            wait_for(f"tick {i + 1}", lambda i=i: attribute(browser, "data-tick") == str(i + 1))
            assert attribute(browser, "data-score") == str(int(info["score"])), i
            assert not (terminated or truncated)
            if i == TICKS // 2:
                illegal_cannot_be_clicked()
        score = int(info["score"])
        state = browser.execute_script("return window.lastState")
        assert state["obs"] == obs.astype(int).tolist()
        assert state["mask"] == info["action_mask"].tolist()
        assert browser.find_element(By.ID, "download").is_displayed()
    finally:
        twin.close()

    status, recording = call(f"{url}api/play/{session_id}/recording")
    assert status == 200
    assert recording["format"] == "dinerdash-play/1" and recording["ruleset"] == "v0"
    assert recording["seed"] == seed and recording["steps"] == TICKS
    assert recording["actions"] == clicks
    assert recording["score"] == score and not recording["finished"]

    rec = tmp_path / "game.json"
    rec.write_text(json.dumps(recording))
    out = tmp_path / "demos"
    assert (
        dinerdash_main(
            ["collect", "--from-play", str(rec), "--out", str(out), "--address", server.address]
        )
        == 0
    )
    with np.load(out / "dinerdash_play.npz") as demos:
        assert demos["actions"].tolist() == clicks
        assert np.array_equal(demos["observations"], np.array(observations[:-1]))
        assert np.array_equal(demos["next_observations"], np.array(observations[1:]))
        assert np.array_equal(demos["action_masks"], np.array(masks[:-1]))
        assert demos["scores"].tolist() == [score]
        assert demos["seeds"].tolist() == [seed]
        assert demos["episode_lengths"].tolist() == [TICKS]
    if importlib.util.find_spec("minari") is not None:
        assert (tmp_path / "minari" / "dinerdash" / "play-v0").is_dir()


@needs_chromium
def test_real_time_mode_waits_at_its_rate(start_server, browser) -> None:
    rate = 5.0
    server = start_server("--http-port", "0")
    url = page_url(server)
    began = time.monotonic()
    browser.get(f"{url}play?seed=3&mode=realtime&rate={rate}")
    session_id = wait_for("a game", lambda: attribute(browser, "data-session-id"))
    wait_for("ticks without clicks", lambda: int(attribute(browser, "data-tick") or 0) >= 5)
    browser.get("about:blank")  # stops the page's clock
    status, recording = call(f"{url}api/play/{session_id}/recording")
    elapsed = time.monotonic() - began
    assert status == 200
    # Nothing but waits, and never faster than the rate (slack for the timer's phase).
    assert set(recording["actions"]) == {0}
    assert 5 <= recording["steps"] <= elapsed * rate + 2


def tenants_server(start_server, tmp_path):
    tokens = tmp_path / "tokens"
    tokens.write_text("team-a team-a-token-aaaa\nteam-b team-b-token-bbbb\n")
    server = start_server("--http-port", "0", "--auth-tokens-file", str(tokens))
    return server, page_url(server, token="team-a-token-aaaa")


def test_another_tenant_gets_what_an_unknown_id_gets(start_server, tmp_path) -> None:
    server, url = tenants_server(start_server, tmp_path)
    a, b = "team-a-token-aaaa", "team-b-token-bbbb"
    assert call(f"{url}api/play?seed=1", "POST")[0] == 401
    status, game = call(f"{url}api/play?seed=1", "POST", token=a)
    assert status == 200
    sid = game["session_id"]
    assert act(url, sid, 0, tick=0, token=a)[0] == 200
    unknown = "0" * 32
    for path in ("", "/recording"):
        theirs = call(f"{url}api/play/{sid}{path}", token=b)
        nobody = call(f"{url}api/play/{unknown}{path}", token=b)
        assert theirs[0] == 404 and theirs == nobody
    assert act(url, sid, 0, token=b) == act(url, unknown, 0, token=b)
    assert act(url, sid, 0, token=b)[0] == 404
    # Untouched by B: A's game is at tick 1 with one action.
    status, recording = call(f"{url}api/play/{sid}/recording", token=a)
    assert status == 200 and recording["actions"] == [0]
    # The game is a session of A's, on A's sessions page only.
    assert any(s["id"] == sid for s in call(f"{url}api/sessions", token=a)[1]["sessions"])
    assert not call(f"{url}api/sessions", token=b)[1]["sessions"]


def test_bad_requests_are_refused(start_server) -> None:
    server = start_server("--http-port", "0")
    url = page_url(server)
    assert call(f"{url}api/play?speed=3", "POST")[0] == 400
    assert call(f"{url}api/play?lives=0", "POST")[0] == 400
    assert call(f"{url}api/play?seed=-1", "POST")[0] == 400
    status, game = call(f"{url}api/play?seed=2&lives=2", "POST")
    assert status == 200 and game["lives"] == 2 and game["config"]["lives"] == 2
    sid = game["session_id"]
    illegal = game["mask"].index(False)
    assert act(url, sid, illegal)[0] == 409
    assert act(url, sid, 57)[0] == 400
    assert act(url, sid, 0, tick=5)[0] == 409
    assert call(f"{url}api/play/{sid}/act", "POST", b"not json")[0] == 400
    assert call(f"{url}api/play/{sid}/act", "POST", b"{" * 5000)[0] == 413
    assert call(f"{url}api/play/{sid}", "POST")[0] == 405
    assert call(f"{url}api/sessions", "POST")[0] == 405
    # None of it was played.
    assert call(f"{url}api/play/{sid}/recording")[1]["actions"] == []


def test_bad_recordings_are_refused_and_nothing_is_written(
    start_server, tmp_path, capsys, monkeypatch
) -> None:
    monkeypatch.setenv("MINARI_DATASETS_PATH", str(tmp_path / "minari"))
    server = start_server("--http-port", "0")
    url = page_url(server)
    status, state = call(f"{url}api/play?seed=8", "POST")
    sid = state["session_id"]
    for _ in range(40):
        status, state = act(url, sid, state["expert"]["reference"], tick=state["tick"])
        assert status == 200
    recording = call(f"{url}api/play/{sid}/recording")[1]
    assert recording["steps"] == 40
    good = tmp_path / "good.json"
    good.write_text(json.dumps(recording))

    def refused(name: str, text: str, needle: str) -> None:
        bad = tmp_path / f"{name}.json"
        bad.write_text(text)
        out = tmp_path / f"out-{name}"
        argv = ["collect", "--from-play", str(good), str(bad), "--out", str(out)]
        assert dinerdash_main([*argv, "--address", server.address]) == 1
        err = capsys.readouterr().err
        assert needle in err and str(bad) in err and "nothing written" in err, err
        assert not out.exists() or not any(out.iterdir())

    refused("notjson", "{", "not a readable JSON recording")
    without_score = {k: v for k, v in recording.items() if k != "score"}
    refused("noscore", json.dumps(without_score), "no 'score'")
    out_of_range = {**recording, "actions": [*recording["actions"][:-1], 99]}
    refused("range", json.dumps(out_of_range), "step 39: action 99")
    refused("ruleset", json.dumps({**recording, "ruleset": "v9"}), "ruleset 'v9'")
    refused("score", json.dumps({**recording, "score": recording["score"] + 1}), "step 39")
    # An action illegal in the replay (seating the 7th group, which is not there): its step.
    wrong = list(recording["actions"])
    wrong[3] = 56
    refused("illegal", json.dumps({**recording, "actions": wrong}), "step 3")
    # The good one alone is written.
    out = tmp_path / "ok"
    argv = ["collect", "--from-play", str(good), "--out", str(out), "--address", server.address]
    assert dinerdash_main(argv) == 0
    with np.load(Path(out) / "dinerdash_play.npz") as demos:
        assert demos["actions"].tolist() == recording["actions"]
        assert demos["scores"].tolist() == [recording["score"]]
    # What `python -m dinerdash_agents train bc --demos` reads accepts it.
    agents_demos = pytest.importorskip("dinerdash_agents.demos")
    loaded = agents_demos.load_demos(Path(out) / "dinerdash_play.npz")
    assert loaded.steps == 40 and loaded.actions.tolist() == recording["actions"]


@needs_chromium
def test_the_replay_page_steps_through_a_recording(start_server, browser, tmp_path) -> None:
    from selenium.webdriver.common.by import By

    server = start_server("--http-port", "0")
    url = page_url(server)
    status, state = call(f"{url}api/play?seed=8&lives=4", "POST")
    sid = state["session_id"]
    for _ in range(30):
        status, state = act(url, sid, state["expert"]["reference"], tick=state["tick"])
    recording = call(f"{url}api/play/{sid}/recording")[1]
    path = tmp_path / "game.json"
    path.write_text(json.dumps(recording))

    browser.get(f"{url}play/replay")
    browser.find_element(By.ID, "replay-file").send_keys(str(path))
    replayed = wait_for("the replay's game", lambda: attribute(browser, "data-session-id"))
    assert replayed != sid
    for i in range(30):
        recorded = browser.find_element(By.CSS_SELECTOR, ".target.recorded")
        assert recorded.get_attribute("data-action") == str(recording["actions"][i])
        browser.find_element(By.ID, "replay-step").click()
        wait_for(f"tick {i + 1}", lambda i=i: attribute(browser, "data-tick") == str(i + 1))
    assert attribute(browser, "data-score") == str(recording["score"])
    assert not browser.find_element(By.ID, "replay-step").is_enabled()
    again = call(f"{url}api/play/{replayed}/recording")[1]
    assert again["actions"] == recording["actions"] and again["config"] == recording["config"]

    # A game of the token's, by its ID.
    browser.get(f"{url}play/replay?from={sid}")
    wait_for("the replay's game", lambda: attribute(browser, "data-session-id") not in ("", sid))
    browser.find_element(By.ID, "replay-step").click()
    wait_for("tick 1", lambda: attribute(browser, "data-tick") == "1")
    # The hints outline the expert's choice; the space bar plays "wait".
    browser.find_element(By.ID, "hint-expert").click()
    expert = browser.execute_script("return window.lastState.expert.reference")
    hinted = browser.find_elements(By.CSS_SELECTOR, ".target.hint")
    assert [h.get_attribute("data-action") for h in hinted] == [str(expert)]
    browser.find_element(By.TAG_NAME, "body").send_keys(" ")
    wait_for("tick 2", lambda: attribute(browser, "data-tick") == "2")
    assert browser.execute_script("return window.lastState.steps") == 2

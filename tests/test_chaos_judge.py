"""The chaos run's judge (``scripts/chaos.py``), tested on itself: it must fail a run whose fault
thread died, that made fewer faults than it scheduled, whose drain or restart cut an episode,
that raised, or whose score fell past the noise, and pass a healthy one.

The judge is a pure function of what the runs recorded, so these tests feed it records; the
fault thread is run for real against a cluster that breaks, to show its death is caught.
"""

from __future__ import annotations

import importlib.util
import random
import sys
import threading
from pathlib import Path

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parent.parent


@pytest.fixture(scope="module")
def chaos():
    spec = importlib.util.spec_from_file_location("chaos_script", ROOT / "scripts" / "chaos.py")
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module  # dataclasses look their module up
    spec.loader.exec_module(module)
    yield module
    del sys.modules[spec.name]


def scores(rng: np.random.Generator, level: float, snapshots: int = 5, seeds: int = 64):
    """(snapshots x seeds) scores like a trained policy's: a per-seed difficulty shared by every
    policy, a per-snapshot training wobble, and per-episode noise."""
    difficulty = np.random.default_rng(7).normal(0.0, 3000.0, seeds)
    wobble = rng.normal(0.0, 500.0, (snapshots, 1))
    return level + difficulty + wobble + rng.normal(0.0, 1500.0, (snapshots, seeds))


def healthy(chaos, began: float = 100.0):
    """A run of 60 s with a kill, a drain and a hang, episodes cut only by the crashes."""
    log = chaos.MonkeyLog(
        faults=[
            chaos.Fault(began + 12.0, "kill", 0, ended=began + 17.0),
            chaos.Fault(began + 30.0, "drain", 1, ended=began + 36.0),
            chaos.Fault(began + 50.0, "hang", 2, ended=began + 55.0),
        ],
        next_due=began + 70.0,
        stopped=began + 60.0,
    )
    rng = np.random.default_rng(0)
    run = chaos.Tally(cuts=[(began + 14.0, 32), (began + 53.0, 32)])
    run.scores = scores(rng, 9000.0)
    calm = chaos.Tally()
    calm.scores = scores(rng, 9000.0)
    return run, log, calm


def test_a_healthy_run_passes(chaos):
    assert chaos.judge(*healthy(chaos)) == []


def test_a_dead_fault_thread_fails_the_run(chaos):
    """The real fault thread, against a cluster whose kill raises: the exception reaches the
    judge instead of ending the thread unseen."""

    class Broken:
        addresses = ("127.0.0.1:1", "127.0.0.1:2", "127.0.0.1:3")

        def __getattr__(self, name):
            def fail(*args, **kwargs):
                raise OSError(f"{name} failed")

            return fail

    class Proxy:
        def blackhole(self):
            raise OSError("blackhole failed")

    class Clock(threading.Event):
        """A stop event whose waits return at once (no real 10-20 s pauses), set after a few."""

        def __init__(self):
            super().__init__()
            self.waits = 0

        def wait(self, timeout=None):
            self.waits += 1
            return self.waits > 20

    log = chaos.MonkeyLog()
    thread = threading.Thread(
        target=chaos._guarded,
        args=(chaos._monkey, Broken(), [Proxy()] * 3, random.Random(0), Clock(), log),
    )
    thread.start()
    thread.join(timeout=30)
    assert not thread.is_alive()
    assert log.error is not None and "failed" in log.error
    run, _, calm = healthy(chaos)
    log.stopped = log.faults[-1].began + 60.0
    failures = chaos.judge(run, log, calm)
    assert any("the fault thread died" in f for f in failures), failures


def test_fewer_faults_than_scheduled_fail(chaos):
    run, log, calm = healthy(chaos)
    log.next_due = log.stopped - 8.0  # due before the stop, and never begun
    failures = chaos.judge(run, log, calm)
    assert any("fewer faults than scheduled" in f for f in failures), failures


def test_a_fault_that_never_ended_fails(chaos):
    run, log, calm = healthy(chaos)
    log.faults[1].ended = None
    failures = chaos.judge(run, log, calm)
    assert any("drain of server 1 began and never ended" in f for f in failures), failures


@pytest.mark.parametrize("kind", ["drain", "restart"])
def test_a_planned_stop_that_cuts_an_episode_fails(chaos, kind):
    run, log, calm = healthy(chaos)
    log.faults[1].kind = kind
    run.cuts.append((log.faults[1].began + 3.0, 32))
    failures = chaos.judge(run, log, calm)
    assert any(f"a {kind} of server 1 cut 32 episodes" in f for f in failures), failures


def test_a_cut_with_no_fault_fails(chaos):
    run, log, calm = healthy(chaos)
    run.cuts.insert(0, (log.faults[0].began - 5.0, 1))
    assert any("no fault begun" in f for f in chaos.judge(run, log, calm))


def test_exceptions_in_either_run_fail(chaos):
    run, log, calm = healthy(chaos)
    calm.exceptions.append("ServiceTimeout: deadline")
    assert any("undisturbed run raised" in f for f in chaos.judge(run, log, calm))
    run, log, calm = healthy(chaos)
    run.exceptions.append("ServerLost: gone")
    assert any("chaos run raised" in f for f in chaos.judge(run, log, calm))


def _fell(failures: list[str]) -> bool:
    return any(f.startswith("the score fell by") for f in failures)


def test_a_fifteen_percent_loss_fails_and_noise_passes(chaos):
    """Across many draws of the noise the judge passes equal runs nearly always and fails a run
    that lost 15 % nearly always (the old bar, the evaluation's unpaired standard error alone,
    let such a loss through). Each draw goes through ``judge`` itself, its score rule included."""
    rng = np.random.default_rng(1)
    run, log, calm = healthy(chaos)
    same = loss = 0
    for _ in range(200):
        calm.scores = scores(rng, 9000.0)
        run.scores = scores(rng, 9000.0)
        same += _fell(chaos.judge(run, log, calm))
        run.scores = scores(rng, 9000.0 * 0.85)
        loss += _fell(chaos.judge(run, log, calm))
    assert same <= 10, same  # about 2.5 % one-sided false alarms
    assert loss >= 190, loss


@pytest.mark.parametrize("bad", [np.nan, np.inf, -np.inf])
def test_a_score_that_is_not_a_number_fails(chaos, bad):
    run, log, calm = healthy(chaos)
    run.scores = run.scores.copy()
    run.scores[0, 0] = bad
    failures = chaos.judge(run, log, calm)
    assert any("the score gap is not a number" in f for f in failures), failures


def test_the_score_gap_is_paired(chaos):
    """The seeds' difficulty, shared by both runs, does not count as noise."""
    rng = np.random.default_rng(2)
    calm = scores(rng, 9000.0, snapshots=1)
    gap, sigma = chaos.score_gap(calm + 100.0, calm)
    assert gap == pytest.approx(100.0) and sigma < 1e-6
    with pytest.raises(ValueError, match="differ in shape"):
        chaos.score_gap(calm[:, :10], calm)

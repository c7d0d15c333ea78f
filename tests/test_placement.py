"""Placement as a pure function (:func:`dinerdash._placement.plan`), property-tested with
hypothesis and no server: whatever the fleet looks like, once a plan's moves are done every
draining server is empty and the serving servers' loads differ by at most one; a draining or
lost server receives nothing; every environment keeps its index and is moved at most once, from
a run its session holds; and every move is a transfer at the environments' episode ends (the
plan has no way to cut an episode)."""

from __future__ import annotations

import dataclasses
import itertools

from dinerdash._placement import Move, SessionView, pieces, plan
from hypothesis import given, settings
from hypothesis import strategies as st


@st.composite
def fleets(draw):
    """A fleet: servers with a state each (serving, draining, lost), and the env's environments
    in contiguous runs of sessions on the serving and draining servers (a lost server's were
    moved by the failover already), as after a failover or a membership change."""
    k = draw(st.integers(1, 6))
    states = draw(
        st.lists(st.sampled_from(["serving", "draining", "lost"]), min_size=k, max_size=k)
    )
    if "serving" not in states:
        states[draw(st.integers(0, k - 1))] = "serving"
    holders = [j for j, state in enumerate(states) if state != "lost"]
    n = draw(st.integers(1, 60))
    cuts = sorted(draw(st.sets(st.integers(1, n - 1), max_size=min(8, n - 1)))) if n > 1 else []
    bounds = [0, *cuts, n]
    sessions = []
    for key, (lo, hi) in enumerate(itertools.pairwise(bounds)):
        server = draw(st.sampled_from(holders))
        sessions.append(SessionView(key, server, ((lo, hi),), hi - lo))
    return states, n, sessions


def _apply(sessions: list[SessionView], moves: list[Move]) -> dict[int, int]:
    """Where each environment is once ``moves`` are done: env index -> server."""
    where = {}
    for s in sessions:
        for lo, hi in s.runs:
            for i in range(lo, hi):
                where[i] = s.server
    by_key = {s.key: s for s in sessions}
    moved: set[int] = set()
    for m in moves:
        source = by_key[m.source]
        assert m.origin == source.server
        assert any(lo <= m.start < m.stop <= hi for lo, hi in source.runs), m
        for i in range(m.start, m.stop):
            assert i not in moved, f"environment {i} moved twice"
            moved.add(i)
            where[i] = m.dest
    return where


@settings(max_examples=400, deadline=None)
@given(fleets())
def test_a_plan_balances_empties_draining_servers_and_keeps_indices(fleet) -> None:
    states, n, sessions = fleet
    targets = [j for j, state in enumerate(states) if state == "serving"]
    draining = {j for j, state in enumerate(states) if state == "draining"}
    loads = {j: 0 for j in range(len(states))}
    for s in sessions:
        loads[s.server] += s.load
    moves = plan(sessions, loads, targets, draining)

    for m in moves:
        assert states[m.dest] == "serving", "a draining or lost server received environments"
        assert isinstance(m, Move) and m.start < m.stop
    where = _apply(sessions, moves)
    assert sorted(where) == list(range(n)), "an environment lost or added"
    after = {j: 0 for j in range(len(states))}
    for server in where.values():
        after[server] += 1
    for j in draining:
        assert after[j] == 0, f"draining server {j} keeps {after[j]} environments"
    serving = [after[j] for j in targets]
    assert max(serving) - min(serving) <= 1, (after, moves)


@settings(max_examples=200, deadline=None)
@given(fleets())
def test_a_plan_is_a_pure_function_of_its_view(fleet) -> None:
    states, _, sessions = fleet
    targets = [j for j, state in enumerate(states) if state == "serving"]
    draining = {j for j, state in enumerate(states) if state == "draining"}
    loads = {j: sum(s.load for s in sessions if s.server == j) for j in range(len(states))}
    frozen = (list(sessions), dict(loads), list(targets), set(draining))
    first = plan(sessions, loads, targets, draining)
    assert plan(sessions, loads, targets, draining) == first
    assert (sessions, loads, targets, draining) == frozen  # the view is not changed


@settings(max_examples=200, deadline=None)
@given(fleets())
def test_a_balanced_fleet_is_left_alone_and_nothing_moves_without_targets(fleet) -> None:
    states, _, sessions = fleet
    draining = {j for j, state in enumerate(states) if state == "draining"}
    loads = {j: sum(s.load for s in sessions if s.server == j) for j in range(len(states))}
    assert plan(sessions, loads, [], draining) == []
    # A session with a transfer under way into it gives nothing.
    busy = [dataclasses.replace(s, busy=True) for s in sessions]
    targets = [j for j, state in enumerate(states) if state == "serving"]
    assert all(m.origin in draining for m in plan(busy, loads, targets, draining))
    serving = [loads[j] for j in targets]
    if not draining and max(serving) - min(serving) <= 1:
        assert plan(sessions, loads, targets, set()) == []


@given(
    st.integers(0, 50),
    st.integers(0, 50),
    st.dictionaries(st.integers(0, 5), st.integers(0, 9), min_size=1),
)
def test_pieces_cover_the_run_evenly(start, length, loads) -> None:
    out = pieces(start, start + length, loads)
    assert [i for a, b, _ in out for i in range(a, b)] == list(range(start, start + length))
    sizes = [b - a for a, b, _ in out]
    assert not sizes or max(sizes) - min(sizes) <= 1 or len(sizes) < len(loads)

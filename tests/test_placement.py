"""Where slices move (:func:`dinerdash._fleet.plan`), property-tested with hypothesis and no
server: whatever the fleet looks like, once a plan's splits are done every draining server is
empty and the serving servers' loads differ by at most one; a draining or lost server receives
nothing; every environment keeps its index; a slice that may not move now is left alone; and a
balanced fleet is left as it is. (The moves themselves, Snapshot and Restore on real servers:
``test_moves.py``.)"""

from __future__ import annotations

import itertools

from dinerdash._fleet import even_parts, plan
from hypothesis import given, settings
from hypothesis import strategies as st


@st.composite
def fleets(draw):
    """A fleet: servers with a state each (serving, draining, lost), and the env's environments
    in contiguous slices on the serving and draining servers (a lost server's were moved by the
    failover already), some of them not movable now (a failover's cut waiting to be reported)."""
    k = draw(st.integers(1, 6))
    states = draw(
        st.lists(st.sampled_from(["serving", "draining", "lost"]), min_size=k, max_size=k)
    )
    if "serving" not in states:
        states[draw(st.integers(0, k - 1))] = "serving"
    holders = [j for j, state in enumerate(states) if state != "lost"]
    n = draw(st.integers(1, 60))
    cuts = sorted(draw(st.sets(st.integers(1, n - 1), max_size=min(8, n - 1)))) if n > 1 else []
    slices = [
        (draw(st.sampled_from(holders)), lo, hi, draw(st.booleans()) or draw(st.booleans()))
        for lo, hi in itertools.pairwise([0, *cuts, n])
    ]
    return states, n, slices


def _apply(slices, splits) -> list[tuple[int, int, int]]:
    """The slices ``(server, start, stop)`` once ``splits`` are done, checking each split."""
    out = {pos: [(server, lo, hi)] for pos, (server, lo, hi, _) in enumerate(slices)}
    for pos, parts in splits:
        server, lo, hi, movable = slices[pos]
        assert movable, f"slice {pos} may not move now"
        assert [i for a, b, _ in parts for i in range(a, b)] == list(range(lo, hi)), parts
        assert all(a < b for a, b, _ in parts), parts
        out[pos] = [(dest, a, b) for a, b, dest in parts]
    return [s for pos in sorted(out) for s in out[pos]]


@settings(max_examples=400, deadline=None)
@given(fleets())
def test_a_plan_balances_empties_draining_servers_and_keeps_indices(fleet) -> None:
    states, n, slices = fleet
    targets = [j for j, state in enumerate(states) if state == "serving"]
    splits = plan(slices, n, targets)
    assert len({pos for pos, _ in splits}) == len(splits), "a slice split twice"
    after = _apply(slices, splits)
    assert [i for _, a, b in after for i in range(a, b)] == list(range(n)), "an index changed"
    moved = {pos for pos, _ in splits}
    for _, parts in splits:
        for _, _, dest in parts:
            assert dest in targets, parts
    if all(movable for *_, movable in slices):
        loads = dict.fromkeys(targets, 0)
        for server, a, b in after:
            assert server in loads, f"server {server} ({states[server]}) keeps environments"
            loads[server] += b - a
        assert max(loads.values()) - min(loads.values()) <= 1, (after, splits)
    for pos, (*_, movable) in enumerate(slices):
        if not movable:
            assert pos not in moved


@settings(max_examples=200, deadline=None)
@given(fleets())
def test_a_balanced_fleet_is_left_alone(fleet) -> None:
    states, n, slices = fleet
    targets = [j for j, state in enumerate(states) if state == "serving"]
    assert plan(slices, n, targets) == plan(list(slices), n, list(targets))  # pure
    once = _apply(slices, plan(slices, n, targets))
    if all(movable for *_, movable in slices):
        again = [(server, a, b, True) for server, a, b in once]
        assert plan(again, n, targets) == []


@given(
    st.integers(0, 50),
    st.integers(0, 50),
    st.dictionaries(st.integers(0, 5), st.integers(0, 9), min_size=1),
)
def test_pieces_cover_the_run_evenly(start, length, loads) -> None:
    out = even_parts(start, start + length, loads)
    assert [i for a, b, _ in out for i in range(a, b)] == list(range(start, start + length))
    sizes = [b - a for a, b, _ in out]
    assert not sizes or max(sizes) - min(sizes) <= 1 or len(sizes) < len(loads)

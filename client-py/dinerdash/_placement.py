"""Placement: which environments of a vector env over several servers should move where, as a
pure function of a view of the fleet (:func:`plan`), with no I/O: the env applies each
:class:`Move` (a session on the destination for a run of environments, each entering it at its
own episode end) and stops at the first the destination refuses.

The view says, per session, which server it is on, which contiguous runs of the env's
environments it holds (and may give: not already promised to a transfer), how many it holds in
all, and whether it is itself a transfer still under way; per server, its load (what it will
hold once the transfers under way are done); and which servers may receive (serving, not
draining, not lost, not resting after a refusal) and which drain.

What a plan promises (``tests/test_placement.py`` checks it with hypothesis, on views without
transfers under way): once its moves are done, every environment of a draining server is on a
serving one and the serving servers' loads differ by at most one; a draining or lost server
receives nothing; every environment keeps its index (a move names a run of the source's own
environments, and none is moved twice); and no environment moves mid-episode (a move is a
transfer: each environment enters its new session at its episode end; only a drain deadline
about to pass cuts episodes, which is the env's decision, not the plan's).
"""

from __future__ import annotations

from dataclasses import dataclass, field

__all__ = ["Move", "SessionView", "pieces", "plan"]


@dataclass(frozen=True)
class SessionView:
    """One session as placement sees it: on ``server``, holding ``runs`` (contiguous ``(start,
    stop)`` runs of the env's indices that are its own and not promised to a transfer),
    ``load`` environments in all; ``busy``: a transfer under way into it."""

    key: int
    server: int
    runs: tuple[tuple[int, int], ...]
    load: int
    busy: bool = False


@dataclass(frozen=True)
class Move:
    """Environments ``start:stop`` of session ``source`` (on server ``origin``) go to a new
    session on server ``dest``, each at its episode end."""

    source: int
    origin: int
    start: int
    stop: int
    dest: int


@dataclass
class _State:
    runs: dict[int, list[tuple[int, int]]]
    loads: dict[int, int]
    moves: list[Move] = field(default_factory=list)

    def move(self, s: SessionView, lo: int, hi: int, dest: int) -> None:
        self.moves.append(Move(s.key, s.server, lo, hi, dest))
        out = []
        for a, b in self.runs[s.key]:
            if b <= lo or a >= hi:
                out.append((a, b))
            else:
                if a < lo:
                    out.append((a, lo))
                if hi < b:
                    out.append((hi, b))
        self.runs[s.key] = out
        self.loads[dest] = self.loads.get(dest, 0) + hi - lo
        self.loads[s.server] = self.loads.get(s.server, 0) - (hi - lo)


def pieces(start: int, stop: int, loads: dict[int, int]) -> list[tuple[int, int, int]]:
    """Environments ``start:stop`` cut into one contiguous piece per server of ``loads``
    (server index -> environments it holds), as ``(start, stop, server)``: the sizes differ by
    at most one, the larger ones go to the servers holding fewest environments (ties: the lower
    index), and empty pieces are left out."""
    order = sorted(loads, key=lambda i: (loads[i], i))
    m, k = stop - start, len(order)
    out = []
    for j, server in enumerate(order):
        size = m // k + (j < m % k)
        if size:
            out.append((start, start + size, server))
            start += size
    return out


def plan(
    sessions: list[SessionView],
    loads: dict[int, int],
    targets: list[int],
    draining: set[int] | frozenset[int] = frozenset(),
) -> list[Move]:
    """The moves that, once done, leave no environment on a draining server and the loads of
    ``targets`` (the servers that may receive) differing by at most one. ``loads``: each
    server's environments once the transfers under way are done.

    Each target's share is the environments of the targets and draining servers over the
    targets, the larger shares (one more) to the targets that hold most already, so that fewest
    move. The draining servers' runs fill the targets short of their share, most short first;
    then each target above its share gives runs to those still short: a whole session when one
    fits, else the end of its largest run. A session with a transfer under way into it gives
    nothing (its own move waits for the next plan)."""
    if not targets:
        return []
    state = _State({s.key: list(s.runs) for s in sessions}, dict(loads))
    total = sum(state.loads.get(j, 0) for j in targets)
    total += sum(hi - lo for s in sessions if s.server in draining for lo, hi in s.runs)
    order = sorted(targets, key=lambda j: (-state.loads.get(j, 0), j))
    share = {j: total // len(targets) + (r < total % len(targets)) for r, j in enumerate(order)}

    def short() -> list[tuple[int, int]]:
        """The targets short of their share, most short first: (server, how many)."""
        out = [(j, share[j] - state.loads.get(j, 0)) for j in targets]
        return sorted([x for x in out if x[1] > 0], key=lambda x: (-x[1], x[0]))

    def give(s: SessionView, lo: int, hi: int) -> None:
        """Run ``lo:hi`` of ``s``, from its end, to the targets short of their share."""
        for dest, need in short():
            if hi <= lo:
                return
            size = min(need, hi - lo)
            state.move(s, hi - size, hi, dest)
            hi -= size

    for s in [s for s in sessions if s.server in draining]:
        for lo, hi in list(state.runs[s.key]):
            give(s, lo, hi)
    for giver in sorted(targets, key=lambda j: (share[j] - state.loads.get(j, 0), j)):
        mine = [s for s in sessions if s.server == giver and not s.busy]
        while state.loads.get(giver, 0) > share[giver] and short():
            k = state.loads[giver] - share[giver]
            choices = [(s, lo, hi) for s in mine for lo, hi in state.runs[s.key]]
            whole = [x for x in choices if x[2] - x[1] <= k and x[2] - x[1] == x[0].load]
            if whole:
                s, lo, hi = max(whole, key=lambda x: (x[2] - x[1], -x[1]))
            elif choices:
                s, lo, hi = max(choices, key=lambda x: (x[2] - x[1], -x[1]))
                lo = max(lo, hi - k)
            else:
                break
            give(s, lo, hi)
    return state.moves

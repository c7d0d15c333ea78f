"""What a loaded machine adds to a timed wait, measured rather than guessed: the seconds the
processes of a test (this one and its servers) spent runnable but waiting for a CPU, read from
Linux's per-thread scheduler statistics (``/proc/<pid>/task/<tid>/schedstat``, its second field:
run-queue time in nanoseconds).

A time bound of the failover and membership tests is ``what the client's design allows`` + a
small fixed slack for the work itself on a quiet machine + this measured wait over the same
interval. On a quiet machine the wait is near zero and the bound is the fixed one; on a 2-core CI
building wheels beside the tests the bound grows by exactly the time those processes were kept
off a CPU, so it does not depend on the machine's load, and a design fault (a wait for the next
timeout rather than ``failover_after``) still shows: that costs seconds while every thread sleeps,
which adds nothing to the wait measured here.

Waits of threads that ran at once are added up (two threads each kept 1 s from a CPU count 2 s):
the bound errs towards generous. A thread that ended within the interval is not counted; where
the statistics are missing (another OS, a kernel without them) the wait reads 0 and the bound is
the fixed one."""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any


class CpuWait:
    """Counts from its making: ``CpuWait(server_pid, ...).seconds()`` is how long this process's
    and those processes' threads waited for a CPU since (threads started since count whole)."""

    def __init__(self, *pids: int) -> None:
        self.pids = (os.getpid(), *pids)
        self.start = self._read()

    @classmethod
    def of(cls, cluster: Any) -> CpuWait:
        """This process's and every server's of a :class:`dinerdash.testing.LocalCluster`."""
        return cls(*(cluster.pid(i) for i in range(len(cluster))))

    def _read(self) -> dict[tuple[int, int], int]:
        out = {}
        for pid in self.pids:
            for task in Path(f"/proc/{pid}/task").glob("*"):  # nothing for a process gone
                try:
                    waited = int((task / "schedstat").read_text().split()[1])
                except (OSError, IndexError, ValueError):
                    continue  # the thread ended, or no statistics
                out[(pid, int(task.name))] = waited
        return out

    def seconds(self) -> float:
        """Seconds waited for a CPU since the making, summed over the threads."""
        now = self._read()
        return sum(max(0, v - self.start.get(k, 0)) for k, v in now.items()) / 1e9

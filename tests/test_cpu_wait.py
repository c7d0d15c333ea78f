""":class:`tests.cpu_wait.CpuWait`, which the failover and membership tests' time bounds lean on:
it reads this machine's scheduler statistics (a bound would silently lose its load part if it
read 0), counts the waits of a child process it is given, and sees CPU contention that the test
makes itself (more busy processes than cores)."""

from __future__ import annotations

import os
import subprocess
import sys
import time
from pathlib import Path

from .cpu_wait import CpuWait

BUSY = "import time\nend = time.monotonic() + 30\nwhile time.monotonic() < end: pass\n"


def test_contention_shows_as_cpu_wait() -> None:
    assert Path(f"/proc/{os.getpid()}/task/{os.getpid()}/schedstat").exists()
    cores = len(os.sched_getaffinity(0))
    children = [subprocess.Popen([sys.executable, "-c", BUSY]) for _ in range(2 * cores + 1)]
    try:
        waited = CpuWait(*(c.pid for c in children))
        end = time.monotonic() + 1.0
        while time.monotonic() < end:  # this thread busy too: more runnable threads than cores
            pass
        # 2 * cores + 2 busy threads on `cores` CPUs for 1 s: about cores + 2 CPU-seconds of
        # waiting in all; a tenth of one is far below that whatever else runs.
        assert waited.seconds() > 0.1
    finally:
        for child in children:
            child.kill()
            child.wait()

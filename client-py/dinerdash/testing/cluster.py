"""``LocalCluster``: n real ``dinerdash-server`` processes on 127.0.0.1, and the ways to lose
them: signals, as a real machine does (docs/client.md#testing-your-own-training-code).
"""

from __future__ import annotations

import os
import signal
import subprocess
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import Any

from ..connection import Connection, split_host_port
from ..errors import ServiceError
from ..server import LocalServer, find_server_binary, server_args

__all__ = ["LocalCluster", "server_args", "wait_stopped"]

#: Seconds a restarted server keeps trying its old port, which a killed process may still hold.
REBIND_TIMEOUT = 10.0


def wait_stopped(pid: int, timeout: float = 5.0) -> None:
    """Waits until every thread of process ``pid`` is stopped (a signal lands after ``kill``
    returns, and a thread on another core may answer meanwhile). Linux only; elsewhere a sleep."""
    tasks = Path(f"/proc/{pid}/task")
    if not tasks.exists():
        time.sleep(0.1)
        return
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        try:
            # "PID (COMM) STATE ...": COMM may hold spaces and ")"; STATE follows the last ")".
            states = [
                (t / "stat").read_text().rsplit(")", 1)[1].split()[0] for t in tasks.iterdir()
            ]
        except (OSError, IndexError):
            if not tasks.exists():
                return  # gone
            states = []  # a thread ended between the listing and the read: look again
        if states and all(state in ("T", "t") for state in states):
            return
        time.sleep(0.005)


def _ready(address: str, timeout: float) -> None:
    """Waits until the server at ``address`` answers a call: its signal handlers are installed
    only once it serves (a ``SIGTERM`` before would kill it)."""
    try:
        Connection(address, connect_timeout=timeout).close()
    except ServiceError:  # any answer (TLS, a token needed) will do; no answer fails later calls
        pass


class LocalCluster:
    """``n`` ``dinerdash-server`` processes on ``127.0.0.1``, for integration tests and chaos runs;
    a server keeps its index and address for the cluster's life.

    Args:
        n: servers to start.
        binary: the server binary (default: see :func:`~dinerdash.server.find_server_binary`).
        startup_timeout: seconds each server may take to listen.
        stop_timeout: seconds between terminate and kill when stopping a server.
        server_flags: the servers' command-line flags as keywords: ``max_sessions=8`` is
            ``--max-sessions 8``, ``drain_timeout=5`` is ``--drain-timeout 5``
            (:func:`server_args`). Every server, those of :meth:`add` too, gets them.
    """

    def __init__(
        self,
        n: int = 3,
        *,
        binary: str | os.PathLike[str] | None = None,
        startup_timeout: float = 30.0,
        stop_timeout: float = 10.0,
        **server_flags: Any,
    ) -> None:
        if isinstance(n, bool) or not isinstance(n, int) or n < 0:
            raise ValueError(f"n: expected a number of servers >= 0, got {n!r}")
        chosen = "a LocalCluster's servers listen on 127.0.0.1 and a port each picks itself"
        self.args = server_args(server_flags, {"host": chosen, "port": chosen})
        self.binary = find_server_binary(binary)
        self.startup_timeout = startup_timeout
        self.stop_timeout = stop_timeout
        self.server_flags = dict(server_flags)
        #: The servers, one per index; a restarted server is a new object at the same index.
        self.servers: list[LocalServer] = []
        self._addresses: list[str] = []
        self._hung: set[int] = set()
        self._launcher = ThreadPoolExecutor(1, thread_name_prefix="dinerdash-cluster-launcher")
        try:
            for _ in range(n):
                self.add()
        except BaseException:
            self.close()
            raise

    @property
    def addresses(self) -> list[str]:
        """``"127.0.0.1:PORT"`` of every server, by index, whether it runs or not."""
        return list(self._addresses)

    def address(self, i: int) -> str:
        return self._addresses[i]

    def __len__(self) -> int:
        return len(self.servers)

    def _start(self, port: int) -> LocalServer:
        # From the cluster's own thread: a server dies with the thread that started it.
        return self._launcher.submit(self._launch, port).result()

    def _launch(self, port: int) -> LocalServer:
        server = LocalServer(
            self.binary,
            port=port,
            args=self.args,
            startup_timeout=self.startup_timeout,
            stop_timeout=self.stop_timeout,
            rebind_timeout=REBIND_TIMEOUT,
        )
        try:
            _ready(server.address, self.startup_timeout)
        except BaseException:
            server.stop()
            raise
        return server

    def add(self) -> int:
        """Starts one more server (with the cluster's flags) on a new port; returns its index."""
        server = self._start(0)
        self.servers.append(server)
        self._addresses.append(server.address)
        return len(self.servers) - 1

    def _process(self, i: int) -> subprocess.Popen:
        return self.servers[i].process

    def pid(self, i: int) -> int:
        """The process id of server ``i`` (a restarted server has a new one)."""
        return self._process(i).pid

    def is_running(self, i: int) -> bool:
        """Whether server ``i``'s process exists (a hung one does)."""
        return self._process(i).poll() is None

    def is_hung(self, i: int) -> bool:
        """Whether server ``i`` is stopped by :meth:`hang` and not resumed yet."""
        return i in self._hung and self.is_running(i)

    def _signal(self, i: int, sig: signal.Signals) -> bool:
        process = self._process(i)
        if process.poll() is not None:
            return False
        try:
            process.send_signal(sig)
        except ProcessLookupError:  # exited between poll and kill
            return False
        return True

    def kill(self, i: int) -> None:
        """``SIGKILL``: server ``i`` crashes; returns when it is gone."""
        self._signal(i, signal.SIGKILL)
        self._process(i).wait()
        self._hung.discard(i)

    def hang(self, i: int) -> None:
        """``SIGSTOP``: server ``i`` answers nothing while its connections stay open; returns once
        it is stopped."""
        if self._signal(i, signal.SIGSTOP):
            self._hung.add(i)
            wait_stopped(self.pid(i))

    def resume(self, i: int) -> None:
        """``SIGCONT``: a hung server ``i`` goes on where it stopped."""
        self._signal(i, signal.SIGCONT)
        self._hung.discard(i)

    def drain(self, i: int) -> None:
        """``SIGTERM``, returning at once: server ``i``'s planned stop (:meth:`wait` for it)."""
        self.resume(i)  # a stopped process would only see the signal once resumed
        self._signal(i, signal.SIGTERM)

    def wait(self, i: int, timeout: float | None = None) -> int:
        """Server ``i``'s exit status once it exits (negative: a signal); :class:`TimeoutError`
        past ``timeout`` seconds."""
        try:
            return self._process(i).wait(timeout)
        except subprocess.TimeoutExpired:
            raise TimeoutError(
                f"server {i} ({self._addresses[i]}) still running after {timeout:g} s"
            ) from None

    def stop(self, i: int) -> None:
        """Stops server ``i`` (resumed first if hung): terminate, wait, kill."""
        self.resume(i)
        self.servers[i].stop()

    def restart(
        self, i: int, *, wait_drain: bool = True, drain_timeout: float | None = None
    ) -> None:
        """Stops server ``i`` if it runs (``wait_drain``: ``SIGTERM`` and wait, ``SIGKILL`` past
        ``drain_timeout`` seconds; else ``SIGKILL`` at once) and starts it again on the same port;
        returns once it serves."""
        if self.is_running(i):
            if wait_drain:
                self.drain(i)
                try:
                    self.wait(i, drain_timeout)
                except TimeoutError:
                    self.kill(i)
            else:
                self.kill(i)
        self.servers[i].stop()  # closes its stderr file; the process is gone already
        self.servers[i] = self._start(split_host_port(self._addresses[i])[1])
        self._hung.discard(i)

    def close(self) -> None:
        """Stops every server, hung ones included; safe to call twice."""
        try:
            for i, server in enumerate(self.servers):
                try:
                    self.resume(i)
                finally:
                    server.stop()
        finally:
            self._hung.clear()
            self._launcher.shutdown(wait=True)

    def __enter__(self) -> LocalCluster:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def __repr__(self) -> str:
        states = []
        for i, address in enumerate(self._addresses):
            state = "hung" if self.is_hung(i) else "up" if self.is_running(i) else "down"
            states.append(f"{address} {state}")
        return f"LocalCluster([{', '.join(states)}])"

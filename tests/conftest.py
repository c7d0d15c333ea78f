"""Fixtures that run the real ``dinerdash-server`` release binary on 127.0.0.1.

The binary is ``DINERDASH_SERVER`` or ``<repo>/target/release/dinerdash-server`` (build it with
``cargo build --release -p dinerdash-server``). Every server listens on a port it picks itself
(``--port 0``) and is stopped by the fixture that started it.
"""

from __future__ import annotations

import os
import re
import signal
import subprocess
import threading
import time
from collections.abc import Iterator
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parent.parent
CONFORMANCE_DIR = REPO / "tests" / "data" / "conformance"
STARTUP_TIMEOUT = 30.0
_LISTENING = re.compile(r"^dinerdash-server listening on (\S+):(\d+)\s*$")


@pytest.hookimpl(hookwrapper=True)
def pytest_runtest_makereport(item, call):
    """In CI (``CI`` set) nothing may skip: a skip there means an extra was not installed or a
    tool is missing, and the test would pass without judging anything. It fails instead."""
    outcome = yield
    report = outcome.get_result()
    if os.environ.get("CI") and report.skipped and not hasattr(report, "wasxfail"):
        report.outcome = "failed"
        report.longrepr = f"skipped in CI, where every test must run: {report.longrepr}"


@pytest.hookimpl(hookwrapper=True)
def pytest_make_collect_report(collector):
    """The same rule for a module that skips as it is collected (a module-level
    ``pytest.importorskip``): in CI its tests would otherwise vanish without a report."""
    outcome = yield
    report = outcome.get_result()
    if os.environ.get("CI") and report.skipped:
        report.outcome = "failed"
        report.longrepr = (
            f"skipped at collection in CI, where every test must run: {report.longrepr}"
        )


def server_binary() -> Path:
    path = Path(
        os.environ.get("DINERDASH_SERVER") or REPO / "target" / "release" / "dinerdash-server"
    )
    if not (path.is_file() and os.access(path, os.X_OK)):
        pytest.fail(
            f"dinerdash-server binary not found at {path}: build it with "
            "`cargo build --release -p dinerdash-server` or set DINERDASH_SERVER",
            pytrace=False,
        )
    return path


def server_env() -> dict[str, str]:
    """The environment for a test server: no auth token or address inherited from the caller."""
    env = dict(os.environ)
    for key in ("DINERDASH_AUTH_TOKEN", "DINERDASH_ADDRESS"):
        env.pop(key, None)
    return env


class ServerProcess:
    """One ``dinerdash-server`` child; ``stop()`` is terminate -> wait -> kill. ``wrapper``: a
    command that runs the server's command line after it; ``pid`` is then the wrapper's. (``unshare
    --pid --fork --kill-child`` ignores SIGTERM while it waits, so ``stop()`` reaches its SIGKILL
    after 10 s; ``kill()`` ends it, and the server with it, at once.)"""

    def __init__(self, *args: str, port: int = 0, wrapper: tuple[str, ...] = ()) -> None:
        self.args = args
        cmd = [*wrapper, str(server_binary()), "--host", "127.0.0.1", "--port", str(port), *args]
        self.proc = subprocess.Popen(
            cmd,
            stdin=subprocess.DEVNULL,
            stdout=subprocess.PIPE,
            stderr=subprocess.DEVNULL,
            env=server_env(),
        )
        line: list[str] = []
        got = threading.Event()

        def pump() -> None:
            for raw in iter(self.proc.stdout.readline, b""):
                if not got.is_set():
                    line.append(raw.decode(errors="replace").rstrip("\n"))
                    got.set()
            got.set()

        threading.Thread(target=pump, daemon=True).start()
        if not got.wait(STARTUP_TIMEOUT) or not line:
            self.stop()
            pytest.fail(
                f"{' '.join(cmd)}: no 'listening on' line within {STARTUP_TIMEOUT} s", pytrace=False
            )
        match = _LISTENING.match(line[0])
        if match is None:
            self.stop()
            pytest.fail(f"{' '.join(cmd)}: unexpected first line {line[0]!r}", pytrace=False)
        self.host, self.port = match.group(1), int(match.group(2))
        self.address = f"{self.host}:{self.port}"

    @property
    def pid(self) -> int:
        return self.proc.pid

    def kill(self) -> None:
        """SIGKILL, as a crash would: no graceful shutdown."""
        if self.proc.poll() is None:
            self.proc.send_signal(signal.SIGKILL)
            self.proc.wait(timeout=10)
        self.proc.stdout.close()

    def stop(self) -> None:
        """SIGTERM, repeated while the server drains (the first one starts a drain that serves
        the sessions left; a later one ends it at once), SIGKILL after 10 s."""
        deadline = time.monotonic() + 10
        while self.proc.poll() is None and time.monotonic() < deadline:
            self.proc.terminate()
            try:
                self.proc.wait(timeout=0.2)
            except subprocess.TimeoutExpired:
                pass
        if self.proc.poll() is None:
            self.proc.kill()
            self.proc.wait(timeout=10)
        self.proc.stdout.close()

    def restart(self) -> ServerProcess:
        """A new server on the same port (the old one must be gone)."""
        deadline = time.monotonic() + 10
        while True:
            try:
                return ServerProcess(*self.args, port=self.port)
            except pytest.fail.Exception:
                if time.monotonic() > deadline:  # the port may linger briefly after a kill
                    raise
                time.sleep(0.2)


@pytest.fixture(autouse=True)
def _hermetic_env(monkeypatch: pytest.MonkeyPatch) -> None:
    """Tests choose their servers explicitly; a developer's DINERDASH_* must not leak in."""
    for key in (
        "DINERDASH_ADDRESS",
        "DINERDASH_AUTH_TOKEN",
        "DINERDASH_TIMEOUT",
        "DINERDASH_TLS_CA",
    ):
        monkeypatch.delenv(key, raising=False)


@pytest.fixture(scope="session")
def server() -> Iterator[ServerProcess]:
    """A server shared by the tests that do not stop or restart it."""
    proc = ServerProcess()
    yield proc
    proc.stop()


@pytest.fixture(scope="session")
def address(server: ServerProcess) -> str:
    return server.address


@pytest.fixture
def start_server() -> Iterator:
    """A factory of servers private to one test; all of them are stopped after it."""
    started: list[ServerProcess] = []

    def start(*args: str, port: int = 0, wrapper: tuple[str, ...] = ()) -> ServerProcess:
        proc = ServerProcess(*args, port=port, wrapper=wrapper)
        started.append(proc)
        return proc

    start.started = started  # restarted servers are registered here too
    yield start
    for proc in started:
        proc.stop()


@pytest.fixture(scope="session")
def conformance_files() -> list[Path]:
    files = sorted(CONFORMANCE_DIR.glob("*.jsonl"))
    if not files:
        pytest.fail(f"no conformance trajectories (*.jsonl) in {CONFORMANCE_DIR}", pytrace=False)
    return files


@pytest.fixture(params=["grpc", "shm"])
def each_transport(request, monkeypatch) -> Iterator[str]:
    """Runs a test once over each transport: every environment the test makes without a
    ``transport=`` of its own steps over ``request.param``; afterwards, every session those
    environments opened must have chosen that transport (which one served is asserted, not
    assumed: a shared-memory run that fell back to gRPC at its start fails here). Environments
    given their own transport (a test through a TCP proxy is gRPC's) are left as they are."""
    from dinerdash import connection
    from dinerdash._session import SessionCore

    transport = request.param
    merged = connection.ConnectOptions.merged.__func__
    injected: list = []  # the options made here, compared by identity
    chosen: list[str] = []

    def with_transport(cls, connect, caller, **keywords):
        if "transport" in keywords or (connect is not None and connect.transport != "auto"):
            return merged(cls, connect, caller, **keywords)
        options = merged(cls, connect, caller, transport=transport, **keywords)
        injected.append(options)
        return options

    attach = SessionCore.attach

    def recorded(core: SessionCore) -> None:
        attach(core)
        if any(core.endpoint.options is o for o in injected):
            chosen.append(core.transport.name)

    monkeypatch.setattr(connection.ConnectOptions, "merged", classmethod(with_transport))
    monkeypatch.setattr(SessionCore, "attach", recorded)
    yield transport
    assert set(chosen) <= {transport}, f"sessions chose {sorted(set(chosen))}, not {transport}"
    request.node.user_properties.append(("transport", transport))
    if injected and any(o.address is not None for o in injected):
        assert chosen, f"environments made over {transport} opened no session"

"""A local ``dinerdash-server`` subprocess (:class:`LocalServer`): the embedded default when no
address is given, and the servers of ``dinerdash.testing`` and ``dinerdash.ray``; where its binary
is found and how it is stopped: docs/install.md#where-the-client-finds-the-server-binary.
"""

from __future__ import annotations

import os
import queue
import re
import shutil
import subprocess
import sys
import tempfile
import threading
import time
import weakref
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

from .errors import LocalServerError, ServerBinaryNotFound

__all__ = ["FlagChosenByCaller", "LocalServer", "find_server_binary", "server_args"]


class FlagChosenByCaller(TypeError, ValueError):
    """A server flag given to a caller that chooses it itself (a ``TypeError`` as for a keyword
    the caller does not take, and a ``ValueError`` as ``LocalCluster`` always raised)."""


def server_args(flags: Mapping[str, Any], chosen: Mapping[str, str] | None = None) -> list[str]:
    """Command-line arguments from keywords: ``max_sessions=8`` is ``--max-sessions 8``; ``True``
    is the bare flag; ``None`` and ``False`` leave the flag out; a list or tuple repeats it. A flag
    named in ``chosen`` is refused (:class:`FlagChosenByCaller`) with its message."""
    for name in flags:
        if chosen and name.replace("-", "_") in chosen:
            raise FlagChosenByCaller(f"{name}: {chosen[name.replace('-', '_')]}")
    args: list[str] = []
    for name, value in flags.items():
        flag = "--" + name.replace("_", "-")
        if value is None or value is False:
            continue
        if value is True:
            args.append(flag)
        elif isinstance(value, (list, tuple)):
            for item in value:
                args += [flag, str(item)]
        else:
            args += [flag, str(value)]
    return args


_LISTENING = re.compile(r"^dinerdash-server listening on (\S+)\s*$")
_PROBES = re.compile(r"^dinerdash-server probes on (\S+)\s*$")
_BUILD_HINT = (
    "install it with `pip install 'dinerdash[server]'`; or, in a clone of the repository, build it "
    "with `cargo build --release -p dinerdash-server` and set "
    "DINERDASH_SERVER=/path/to/target/release/dinerdash-server or put it on PATH; or connect to a "
    "running server with address='host:port' (or DINERDASH_ADDRESS)"
)


def find_server_binary(binary: str | os.PathLike[str] | None = None) -> Path:
    """The ``dinerdash-server`` binary to start, or :class:`ServerBinaryNotFound` saying how to
    get one."""
    if binary is not None:
        candidates = [("binary argument", binary)]
    else:
        # client-py/dinerdash/server.py -> the workspace root holds target/release.
        workspace = Path(__file__).resolve().parent.parent.parent
        exe = "dinerdash-server.exe" if os.name == "nt" else "dinerdash-server"
        candidates = [
            ("DINERDASH_SERVER", os.environ.get("DINERDASH_SERVER") or None),
            ("dinerdash-server package", _wheel_binary()),
            ("PATH", shutil.which("dinerdash-server")),
            ("workspace", workspace / "target" / "release" / exe),
        ]
    tried = []
    for origin, where in candidates:
        if where is None:
            continue
        path = Path(where)
        if path.is_file() and os.access(path, os.X_OK):
            return path
        tried.append(f"{path} ({origin})")
        if origin in ("binary argument", "DINERDASH_SERVER"):
            break  # an explicit choice that is wrong is an error, not a hint to look elsewhere
    raise ServerBinaryNotFound(
        f"no dinerdash-server binary found (tried {', '.join(tried)}); {_BUILD_HINT}"
    )


def _wheel_binary() -> Path | None:
    """The binary of the installed ``dinerdash-server`` wheel (the ``[server]`` extra), if any."""
    try:
        from dinerdash_server import find_binary
    except ImportError:
        return None
    try:
        return Path(find_binary())
    except FileNotFoundError:  # the package without its binary: a broken install, look on
        return None


def _death_signal() -> list[str]:
    """The command prefix that makes the server die with the thread that started it: ``setpriv
    --pdeathsig TERM`` where there is one (Linux), else nothing; not a ``preexec_fn`` (why:
    docs/install.md#where-the-client-finds-the-server-binary)."""
    if not sys.platform.startswith("linux"):
        return []
    setpriv = shutil.which("setpriv")
    return [setpriv, "--pdeathsig", "TERM", "--"] if setpriv else []


#: ``--max-envs-per-session`` of a local server unless its ``args`` set one: the most the flag
#: allows (the server is this client's alone; its memory budget still bounds the sessions).
LOCAL_MAX_ENVS_PER_SESSION = 65_536

#: Seconds between the SIGTERMs that stop a server (the first starts its drain, the next ends it).
_SIGTERM_EVERY = 0.2


def _stop_process(proc: subprocess.Popen, timeout: float) -> None:
    """Stops ``proc`` at once: SIGTERM, again while it drains, and SIGKILL after ``timeout``."""
    deadline = time.monotonic() + timeout
    while proc.poll() is None and time.monotonic() < deadline:
        proc.terminate()
        try:
            proc.wait(timeout=min(_SIGTERM_EVERY, max(0.0, deadline - time.monotonic())))
        except subprocess.TimeoutExpired:
            pass
    if proc.poll() is None:
        proc.kill()
        proc.wait()
    if proc.stdout is not None:
        proc.stdout.close()


class LocalServer:
    """A ``dinerdash-server`` child process on ``127.0.0.1`` and a port the server picks; a
    context manager, or call :meth:`stop` (also run when collected and at interpreter exit).

    Args:
        binary: path of the binary (default: see :func:`find_server_binary`).
        host: interface to listen on.
        port: port to listen on; 0 lets the server pick a free one.
        args: extra command-line arguments for the server (e.g. ``["--max-sessions", "8"]``);
            unless they set ``--max-envs-per-session``, it is :data:`LOCAL_MAX_ENVS_PER_SESSION`.
        startup_timeout: seconds to wait for the ``listening on`` line (and, given
            ``--probe-port``, the ``probes on`` line: :attr:`probe_address`).
        stop_timeout: seconds between terminate and kill.
        rebind_timeout: seconds to keep trying a given ``port`` that a stopped server has not
            let go of yet (a restart on the same port).
    """

    def __init__(
        self,
        binary: str | os.PathLike[str] | None = None,
        *,
        host: str = "127.0.0.1",
        port: int = 0,
        args: Sequence[str] = (),
        startup_timeout: float = 30.0,
        stop_timeout: float = 10.0,
        rebind_timeout: float = 0.0,
    ) -> None:
        self.binary = find_server_binary(binary)
        self.host = host
        self.port = port
        self.args = list(args)
        self.startup_timeout = startup_timeout
        self.stop_timeout = stop_timeout
        self.address: str | None = None
        #: Where the probe listener serves health, given ``--probe-port`` in ``args``.
        self.probe_address: str | None = None
        self.process: subprocess.Popen | None = None
        self._stderr = None
        self._finalizer: weakref.finalize | None = None
        deadline = time.monotonic() + rebind_timeout
        while True:
            try:
                self.start()
                break
            except LocalServerError:
                if not port or time.monotonic() > deadline:
                    raise
                time.sleep(0.1)

    @property
    def pid(self) -> int | None:
        """The server's process id while it runs."""
        return self.process.pid if self.process is not None else None

    def start(self) -> None:
        """Starts the server and waits until it listens."""
        if self.process is not None and self.process.poll() is None:
            return
        # stderr goes to a file: nobody drains a pipe, and its tail explains a failed start.
        self._stderr = tempfile.TemporaryFile(mode="w+b")
        cmd = [str(self.binary), "--host", self.host, "--port", str(self.port), *self.args]
        if not any(a.split("=")[0] == "--max-envs-per-session" for a in self.args):
            cmd += ["--max-envs-per-session", str(LOCAL_MAX_ENVS_PER_SESSION)]
        try:
            self.process = subprocess.Popen(
                [*_death_signal(), *cmd],
                stdin=subprocess.DEVNULL,
                stdout=subprocess.PIPE,
                stderr=self._stderr,
            )
        except OSError as e:
            raise LocalServerError(f"could not start {cmd[0]}: {e}; {_BUILD_HINT}") from None
        self._finalizer = weakref.finalize(self, _stop_process, self.process, self.stop_timeout)
        lines: queue.Queue[str | None] = queue.Queue()
        threading.Thread(
            target=_pump,
            args=(self.process.stdout, lines),
            name="dinerdash-server-stdout",
            daemon=True,
        ).start()
        deadline = time.monotonic() + self.startup_timeout
        probed = any(a.split("=")[0] == "--probe-port" for a in self.args)
        self.probe_address = None  # a restart's is read again (port 0 picks a new one)
        while True:
            try:
                line = lines.get(timeout=max(0.0, deadline - time.monotonic()))
            except queue.Empty:
                tail = self._stderr_tail()
                self.stop()
                raise LocalServerError(
                    f"{' '.join(cmd)} did not print 'dinerdash-server listening on HOST:PORT' "
                    f"within {self.startup_timeout:g} s{tail}"
                ) from None
            if line is None:  # stdout closed: the server exited
                code = self.process.wait()
                tail = self._stderr_tail()
                self.stop()
                raise LocalServerError(
                    f"{' '.join(cmd)} exited with status {code} before listening{tail}"
                )
            if (match := _LISTENING.match(line)) is not None:
                self.address = match.group(1)
            elif (match := _PROBES.match(line)) is not None:
                self.probe_address = match.group(1)
            if self.address is not None and (self.probe_address is not None or not probed):
                return

    def _stderr_tail(self) -> str:
        if self._stderr is None:
            return ""
        try:
            self._stderr.seek(0)
            tail = self._stderr.read()[-2000:].decode(errors="replace").strip()
        except (OSError, ValueError):
            return ""
        return f"; its stderr:\n{tail}" if tail else ""

    def is_running(self) -> bool:
        return self.process is not None and self.process.poll() is None

    def stop(self) -> None:
        """Stops the server (terminate, wait, kill); safe to call twice."""
        if self._finalizer is not None:
            self._finalizer()  # runs _stop_process once, and detaches it from interpreter exit
        if self._stderr is not None:
            self._stderr.close()
            self._stderr = None

    close = stop

    def __enter__(self) -> LocalServer:
        return self

    def __exit__(self, *exc: object) -> None:
        self.stop()

    def __repr__(self) -> str:
        state = "running" if self.is_running() else "stopped"
        return f"LocalServer({self.address!r}, pid={self.pid}, {state})"


def _pump(stream, lines: queue.Queue) -> None:
    """Reads the server's stdout to its end, line by line into ``lines`` (``None`` at the end), so
    that the server never blocks on a full pipe."""
    try:
        for raw in iter(stream.readline, b""):
            lines.put(raw.decode(errors="replace").rstrip("\n"))
    except (OSError, ValueError):
        pass
    lines.put(None)

"""The same-host shared-memory data plane (``transport=``): refusals typed as over gRPC, the
fallbacks, and what either side's ``kill -9`` leaves behind (nothing: no memfd in the server, no
file in /dev/shm), and a client that stops reading, which stalls nobody.

Whom the client trusts: only a server on this host, and only a doorbell whose peer is that
server (this user's uid, the pid its reply announced); anything else is told nothing, and the
session steps over gRPC, the reason logged at debug level. A real server in a pid namespace of
its own (as in a container sharing the host's network) is such a case."""

from __future__ import annotations

import array
import dataclasses
import fcntl
import logging
import os
import select
import shutil
import signal
import socket
import struct
import subprocess
import sys
import termios
import textwrap
import time
from types import SimpleNamespace

import grpc
import numpy as np
import pytest
from dinerdash import (
    Connection,
    ConnectOptions,
    DinerDashEnv,
    DinerDashVectorEnv,
    InvalidArgument,
    ServiceTransportError,
    _shm,
)
from dinerdash._proto import pb, pb_grpc

pytestmark = pytest.mark.skipif(sys.platform != "linux", reason="shared memory needs Linux")

#: Longest any wait here lasts: far above what it takes, so that load cannot fail a test.
PATIENCE = 60.0


def regions(pid: int) -> int:
    """The session regions (memfds) process ``pid`` holds open."""
    count = 0
    for fd in os.listdir(f"/proc/{pid}/fd"):
        try:
            count += os.readlink(f"/proc/{pid}/fd/{fd}").startswith("/memfd:dinerdash-session")
        except OSError:
            pass  # closed meanwhile
    return count


def open_fds(pid: int) -> int:
    return len(os.listdir(f"/proc/{pid}/fd"))


def wait_until(condition, what: str) -> None:
    deadline = time.monotonic() + PATIENCE
    while not condition():
        if time.monotonic() > deadline:
            pytest.fail(f"not within {PATIENCE:g} s: {what}")
        time.sleep(0.05)


def test_the_region_is_used_and_refuses_bad_actions_as_grpc_does(server) -> None:
    envs = {t: DinerDashVectorEnv(3, server.address, transport=t) for t in ("shm", "grpc")}
    try:
        assert regions(server.pid) >= 1
        refused = {}
        for transport, env in envs.items():
            env.reset(seed=1)
            core = env.fleet.cores[0]
            # Past the client's own check, as a client of another language could send them.
            bad = np.array([0, 57, 0], dtype="<i4").tobytes()
            with pytest.raises(InvalidArgument) as e:
                core.step(bad)
            refused[transport] = e.value
            env.step(np.zeros(3, dtype=np.int64))  # the refused step changed nothing
        shm, grpc = refused["shm"], refused["grpc"]
        assert (shm.details, shm.reason, shm.field, shm.env_index, shm.code) == (
            grpc.details,
            grpc.reason,
            grpc.field,
            grpc.env_index,
            grpc.code,
        )
        assert shm.reason == "ACTION_OUT_OF_RANGE" and shm.env_index == 1
    finally:
        for env in envs.values():
            env.close()


def test_shm_away_from_the_server_says_why_and_auto_falls_back(start_server) -> None:
    bare = start_server("--max-shm-sessions", "0")
    with pytest.raises(ServiceTransportError, match="offers no shared memory"):
        DinerDashEnv(bare.address, transport="shm")
    env = DinerDashEnv(bare.address)  # auto: gRPC
    try:
        env.reset(seed=0)
        env.step(0)
        assert regions(bare.pid) == 0
        # What a client on another machine meets: a doorbell name not bound on its host.
        offer = _shm.Offer(env.session_id, "dinerdash-0-on-another-host", b"s" * 32, bare.pid)
        with Connection(env.address) as conn:
            with pytest.raises(ServiceTransportError, match="not on this machine"):
                _shm.open_for(offer, conn, "shm")
    finally:
        env.close()
    with pytest.raises(ValueError, match="transport"):
        ConnectOptions(transport="tcp")


_CLIENT = textwrap.dedent(
    """
    import sys
    import numpy as np
    from dinerdash import DinerDashVectorEnv
    env = DinerDashVectorEnv(64, sys.argv[1], transport="shm")
    env.reset(seed=0)
    env.step(np.zeros(64, dtype=np.int64))
    print("stepping", flush=True)  # in the loop from here on: killed while it steps
    while True:
        env.step(np.zeros(64, dtype=np.int64))
    """
)


def test_a_killed_client_leaves_nothing_and_others_step_on(start_server) -> None:
    server = start_server()
    shm_before = sorted(os.listdir("/dev/shm"))
    other = DinerDashVectorEnv(4, server.address, transport="shm")
    try:
        other.reset(seed=0)
        baseline = open_fds(server.pid)
        for _ in range(2):
            client = subprocess.Popen(
                [sys.executable, "-c", _CLIENT, server.address],
                stdout=subprocess.PIPE,
                stderr=subprocess.DEVNULL,
            )
            try:
                # It has stepped through its region and steps on without a pause.
                assert client.stdout.readline().strip() == b"stepping"
                assert regions(server.pid) == 2
            finally:
                client.send_signal(signal.SIGKILL)
                client.wait(timeout=PATIENCE)
                client.stdout.close()
            wait_until(lambda: regions(server.pid) == 1, "the killed client's region freed")
            wait_until(lambda: open_fds(server.pid) == baseline, "the fd count back to baseline")
            for _ in range(20):
                other.step(np.zeros(4, dtype=np.int64))
        assert sorted(os.listdir("/dev/shm")) == shm_before
    finally:
        other.close()


@pytest.mark.parametrize("transport", ["grpc", "shm"])
def test_a_killed_server_gives_the_same_typed_error(start_server, transport: str) -> None:
    server = start_server()
    env = DinerDashVectorEnv(64, server.address, transport=transport)
    try:
        env.reset(seed=0)
        env.step(np.zeros(64, dtype=np.int64))
        env.step_async(np.zeros(64, dtype=np.int64))
        server.kill()
        with pytest.raises(ServiceTransportError):
            try:
                env.step_wait()  # the step in flight, or the next one, meets the dead server
            except ServiceTransportError:
                raise
            else:
                env.step(np.zeros(64, dtype=np.int64))
    finally:
        env.close()


def _unread(sock: socket.socket) -> int:
    """Bytes of the next message waiting in ``sock`` (a ``SOCK_SEQPACKET``), 0 when none."""
    return struct.unpack("i", fcntl.ioctl(sock, termios.FIONREAD, b"\0\0\0\0"))[0]


def _hung_up(sock: socket.socket) -> bool:
    poller = select.poll()
    poller.register(sock, select.POLLHUP)
    return bool(poller.poll(0))


def test_a_client_that_stops_reading_stalls_nobody(start_server) -> None:
    """A client that rings the doorbell and never reads its replies: the server steps it and
    queues the replies without waiting for it (a full queue makes it hang up), and another
    client's Steps are answered all the while. The stuck client speaks the wire protocol
    itself (docs/shm.md): a session over gRPC, the hello, then ``S`` after ``S``."""
    server = start_server()
    other = DinerDashVectorEnv(8, server.address, transport="shm")
    channel = grpc.insecure_channel(server.address)
    stub = pb_grpc.DinerDashStub(channel)
    stuck = socket.socket(socket.AF_UNIX, socket.SOCK_SEQPACKET | socket.SOCK_CLOEXEC)
    try:
        other.reset(seed=1)
        created = stub.CreateSession(pb.CreateSessionRequest(num_envs=8), timeout=PATIENCE)
        stub.Reset(pb.ResetRequest(session_id=created.session_id, seed=0), timeout=PATIENCE)
        stuck.settimeout(PATIENCE)
        stuck.connect("\0" + created.shm_doorbell)
        stuck.sendall(b"H" + created.session_id.encode() + created.shm_secret)
        reply, ancillary, _, _ = stuck.recvmsg(16, socket.CMSG_SPACE(4))
        assert reply == b"R"
        for _, _, data in ancillary:
            for fd in array.array("i", data):
                os.close(fd)  # the region: not needed to ring the doorbell
        wait_until(lambda: regions(server.pid) == 2, "the stuck client's region made")

        # One ring a round, never a read; the other client steps each round. A round counts
        # when, after the other's Step, the stuck client's replies wait unread and the server
        # has not hung up on it: that Step was served while the stuck one was stuck.
        served_while_stuck = 0
        deadline = time.monotonic() + PATIENCE
        while not _hung_up(stuck):
            assert time.monotonic() < deadline, "the server never hung up on the stuck client"
            try:
                stuck.send(b"S", socket.MSG_DONTWAIT)
            except BlockingIOError:
                pass  # its side is full too: ring again next round
            except (BrokenPipeError, ConnectionResetError):
                break
            other.step(np.zeros(8, dtype=np.int64))
            served_while_stuck += _unread(stuck) > 0 and not _hung_up(stuck)
        assert served_while_stuck >= 2, served_while_stuck
        # The stuck one's region is given up; the other steps on.
        wait_until(lambda: regions(server.pid) == 1, "the unread session's region freed")
        for _ in range(20):
            other.step(np.zeros(8, dtype=np.int64))
    finally:
        stuck.close()
        channel.close()
        other.close()


def test_closing_envs_unmaps_their_regions(server) -> None:
    def mapped() -> int:
        with open("/proc/self/maps") as f:
            return sum("dinerdash-session" in line for line in f)

    # One mapping, and the one descriptor Python's mmap keeps, per open env; both go at close.
    # (The process's other fds come and go with gRPC's threads, so they are not counted.)
    before = (mapped(), regions(os.getpid()))
    for _ in range(3):
        env = DinerDashVectorEnv(8, server.address, transport="shm")
        env.reset(seed=0)
        env.step(np.zeros(8, dtype=np.int64))
        assert (mapped(), regions(os.getpid())) == (before[0] + 1, before[1] + 1)
        env.close()
    assert (mapped(), regions(os.getpid())) == before


class _Core:
    """What :func:`dinerdash._shm.open_for` is given for a session, for a server at ``address``
    that is never called; ``attach()`` as the session core calls it, ``channel`` its shared-memory
    channel (``None``: gRPC)."""

    def __init__(self, address: str, transport: str) -> None:
        self.conn = SimpleNamespace(address=address, timeout=5.0, _closed=False)
        self.transport = transport
        self.session_id = "ab" * 16
        self.offer = None
        self.channel = None

    def attach(self) -> None:
        transport = _shm.open_for(self.offer, self.conn, self.transport)
        self.channel = getattr(transport, "channel", None)


def _offered(core: _Core, doorbell: str, secret: bytes, pid: int) -> None:
    reply = pb.CreateSessionResponse(
        session_id=core.session_id, shm_doorbell=doorbell, shm_secret=secret, shm_server_pid=pid
    )
    core.offer = _shm.Offer.of(reply)


def _this_hosts_address() -> str | None:
    """This host's address on its default route (no packet is sent), if it has one."""
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as probe:
        try:
            probe.connect(("192.0.2.1", 9))
        except OSError:
            return None
        return probe.getsockname()[0]


def test_only_a_server_on_this_host_is_offered_shared_memory(monkeypatch, caplog) -> None:
    assert _shm._on_this_host("127.0.0.1:50051")
    assert _shm._on_this_host("localhost:50051")
    assert _shm._on_this_host("[::1]:50051")
    own = _this_hosts_address()
    if own is not None:
        assert _shm._on_this_host(f"{own}:50051")
    assert not _shm._on_this_host("192.0.2.1:50051")  # TEST-NET-1: never this host's
    assert not _shm._on_this_host("no-such-host.invalid:50051")

    def no_doorbell(*args, **kwargs):
        raise AssertionError("a doorbell was tried for a server on another host")

    monkeypatch.setattr(_shm, "Channel", no_doorbell)
    remote = _Core("192.0.2.1:50051", "shm")
    _offered(remote, "dinerdash-1-remote", b"s" * 32, 1)
    with pytest.raises(ServiceTransportError, match="not on this machine"):
        remote.attach()
    remote.transport = "auto"
    with caplog.at_level(logging.DEBUG, logger="dinerdash"):
        remote.attach()
    assert remote.channel is None
    assert "steps over gRPC: the server at 192.0.2.1:50051 is not on this machine" in caplog.text


def test_a_server_that_sends_no_secret_or_pid_gets_grpc(monkeypatch, caplog) -> None:
    monkeypatch.setattr(_shm, "Channel", None)  # never reached
    for secret, pid in ((b"", os.getpid()), (b"s" * 32, 0)):
        old = _Core("127.0.0.1:50051", "auto")
        _offered(old, "dinerdash-1-old", secret, pid)
        caplog.clear()
        with caplog.at_level(logging.DEBUG, logger="dinerdash"):
            old.attach()
        assert old.channel is None
        assert "no session secret or pid" in caplog.text


def _fake_doorbell() -> tuple[socket.socket, str]:
    """A listening abstract socket of this process, under a fresh name."""
    name = f"dinerdash-fake-{os.getpid()}-{time.monotonic_ns()}"
    fake = socket.socket(socket.AF_UNIX, socket.SOCK_SEQPACKET)
    fake.bind("\0" + name)
    fake.listen(4)
    fake.settimeout(PATIENCE)
    return fake, name


@pytest.mark.parametrize("transport", ["auto", "shm"])
def test_a_doorbell_answered_by_another_process_is_told_nothing(
    server, caplog, transport: str
) -> None:
    fake, name = _fake_doorbell()
    env = DinerDashEnv(server.address, transport=transport)
    try:
        env.reset(seed=0)
        core = env._core
        assert env.transports == {server.address: "shm"}
        # The server's announced pid, but another process answers under the doorbell's name
        # (this test's: as a process that took the name of a server gone would).
        core.offer = dataclasses.replace(core.offer, doorbell=name)
        caplog.clear()
        with caplog.at_level(logging.DEBUG, logger="dinerdash"):
            if transport == "shm":
                with pytest.raises(ServiceTransportError, match="not the server's pid"):
                    core.attach()
            else:
                core.attach()
        assert env.transports == {server.address: "grpc"}
        if transport == "auto":
            assert (
                f"the doorbell is not the server's: the doorbell {name!r} is answered by pid "
                f"{os.getpid()}, not the server's pid {server.pid}"
            ) in caplog.text
        conn, _ = fake.accept()
        with conn:
            conn.settimeout(PATIENCE)
            assert conn.recv(4096) == b""  # closed without a hello: no ID, no secret
        env.step(0)  # over gRPC
    finally:
        env.close()
        fake.close()


_OTHER_USER_DOORBELL = textwrap.dedent(
    """
    import socket, sys
    fake = socket.socket(socket.AF_UNIX, socket.SOCK_SEQPACKET)
    fake.bind("\\0" + sys.argv[1])
    fake.listen(4)
    print("ready", flush=True)
    conn, _ = fake.accept()
    conn.settimeout(60)
    print(conn.recv(4096).hex() or "nothing", flush=True)
    """
)


def _python_for(uid: int) -> str | None:
    """A Python interpreter that user ``uid`` can run (a virtualenv under root's home may not
    be one)."""
    for python in (sys.executable, shutil.which("python3"), "/usr/bin/python3"):
        if python is None:
            continue
        try:
            ran = subprocess.run(
                [python, "-c", "pass"], user=uid, group=uid, cwd="/", timeout=PATIENCE
            )
        except OSError:
            continue
        if ran.returncode == 0:
            return python
    return None


@pytest.mark.skipif(os.geteuid() != 0, reason="a doorbell of a second user needs root to make")
def test_a_doorbell_of_another_user_is_told_nothing(server, caplog) -> None:
    python = _python_for(65534)
    if python is None:
        pytest.skip("no Python interpreter that uid 65534 may run")
    name = f"dinerdash-other-user-{os.getpid()}-{time.monotonic_ns()}"
    fake = subprocess.Popen(
        [python, "-c", _OTHER_USER_DOORBELL, name],
        stdout=subprocess.PIPE,
        user=65534,
        group=65534,
        extra_groups=[],
        cwd="/",
    )
    env = DinerDashEnv(server.address)
    try:
        assert fake.stdout.readline().strip() == b"ready"
        env.reset(seed=0)
        core = env._core
        # Its pid is the one announced: only the uid tells it from the server.
        core.offer = dataclasses.replace(core.offer, doorbell=name, pid=fake.pid)
        with caplog.at_level(logging.DEBUG, logger="dinerdash"):
            core.attach()
        assert env.transports == {server.address: "grpc"}
        assert f"is answered by uid 65534, not this user (uid {os.geteuid()})" in caplog.text
        assert fake.stdout.readline().strip() == b"nothing"
        env.step(0)
    finally:
        env.close()
        fake.kill()
        fake.wait(timeout=PATIENCE)
        fake.stdout.close()


@pytest.mark.skipif(os.geteuid() != 0, reason="a server in a pid namespace of its own needs root")
def test_a_server_in_another_pid_namespace_is_told_nothing_and_auto_steps_over_grpc(
    start_server, caplog
) -> None:
    # As a server in a container that shares the host's network but not its pids: it announces
    # its own pid (1 there), and this process sees it under another.
    server = start_server(wrapper=("unshare", "--pid", "--fork", "--kill-child"))
    with pytest.raises(ServiceTransportError, match="runs in another pid namespace"):
        DinerDashEnv(server.address, transport="shm")
    with caplog.at_level(logging.DEBUG, logger="dinerdash"):
        env = DinerDashEnv(server.address)  # auto
    try:
        env.reset(seed=0)
        for _ in range(20):
            env.step(0)
        assert env.transports == {server.address: "grpc"} and env.transport_changes == 0
        assert "not the server's pid 1" in caplog.text
    finally:
        env.close()
        server.kill()  # unshare ignores SIGTERM while it waits; its child dies with it


def test_a_forked_session_attaches_with_its_own_secret(server) -> None:
    env = DinerDashEnv(server.address, transport="shm")
    child = None
    try:
        env.reset(seed=3)
        child = env.fork()
        offer = child._core.offer
        assert len(offer.secret) == 32 and offer.secret != env._core.offer.secret
        assert repr(offer.secret) not in repr(offer)
        for _ in range(3):
            (obs, reward, *_), (twin, twin_reward, *_) = env.step(1), child.step(1)
            assert np.array_equal(obs, twin) and reward == twin_reward
        assert child.transports == {server.address: "shm"}
    finally:
        if child is not None:
            child.close()
        env.close()

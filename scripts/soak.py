#!/usr/bin/env python3
"""A bounded load-and-abuse run against one server (``make soak``).

Well-behaved trainers step their sessions while hostile clients, on their own connections, try
what issue 12 found: a loop of 1024-environment sessions and forks (memory), Rollout streams
opened and never read or cancelled at once (workers), bytes that do not decode, mangled snapshots,
and silent TCP connections. At the end it prints the server's peak RSS, the trainers' Step p50 /
p99, their errors and the sessions they lost, and what the hostile clients were told.

    .venv/bin/python scripts/soak.py                       # starts target/release/dinerdash-server
    .venv/bin/python scripts/soak.py --duration 60         # a short run
    .venv/bin/python scripts/soak.py --address HOST:PORT   # an already running server (no RSS)

Exit status 1 when a trainer lost a session or saw an error, or the server died.
"""

from __future__ import annotations

import argparse
import collections
import os
import random
import socket
import statistics
import subprocess
import sys
import threading
import time
from pathlib import Path

import grpc
from dinerdash._proto import pb, pb_grpc  # the client package installed by `make venv`
from dinerdash.game import NUM_ACTIONS

ROOT = Path(__file__).resolve().parent.parent


class Tally:
    """Thread-safe counters of what happened, by (who, what)."""

    def __init__(self) -> None:
        self.lock = threading.Lock()
        self.counts: collections.Counter[tuple[str, str]] = collections.Counter()

    def add(self, who: str, what: str, n: int = 1) -> None:
        with self.lock:
            self.counts[(who, what)] += n


def code_of(e: grpc.RpcError) -> str:
    return e.code().name if isinstance(e, grpc.Call) else "TRANSPORT"


def stub(address: str) -> tuple[grpc.Channel, pb_grpc.DinerDashStub]:
    """A client on its own connection (a channel with a private subchannel pool)."""
    channel = grpc.insecure_channel(
        address,
        options=[
            ("grpc.use_local_subchannel_pool", 1),
            ("grpc.max_receive_message_length", 64 << 20),
        ],
    )
    return channel, pb_grpc.DinerDashStub(channel)


def trainer(
    address: str, stop: threading.Event, tally: Tally, latencies: list[float]
) -> None:
    """Creates a 64-environment session and steps it with random actions until told to stop."""
    channel, dd = stub(address)
    rng = random.Random(os.getpid() ^ threading.get_ident())
    n = 64
    try:
        sid = dd.CreateSession(
            pb.CreateSessionRequest(num_envs=n, seed=1), timeout=30
        ).session_id
        dd.Reset(pb.ResetRequest(session_id=sid, seed=1), timeout=30)
        while not stop.is_set():
            actions = b"".join(
                rng.randrange(NUM_ACTIONS).to_bytes(4, "little") for _ in range(n)
            )
            started = time.perf_counter()
            try:
                dd.Step(pb.StepRequest(session_id=sid, actions=actions), timeout=30)
            except grpc.RpcError as e:
                tally.add(
                    "trainer",
                    "session lost" if code_of(e) == "NOT_FOUND" else code_of(e),
                )
                if code_of(e) == "NOT_FOUND":
                    return
                continue
            latencies.append(time.perf_counter() - started)
            tally.add("trainer", "steps")
        dd.CloseSession(pb.CloseSessionRequest(session_id=sid), timeout=30)
    except grpc.RpcError as e:
        tally.add("trainer", f"setup {code_of(e)}")
    finally:
        channel.close()


def memory_hog(address: str, stop: threading.Event, tally: Tally) -> None:
    """Creates 1024-environment sessions and forks them as fast as the server allows; when its
    connection's share is spent it opens another connection, so it runs into the server's whole
    memory budget."""
    channel, dd = stub(address)
    held: list[str] = []
    try:
        while not stop.is_set():
            try:
                if held and random.random() < 0.5:
                    sid = dd.Fork(
                        pb.ForkRequest(session_id=random.choice(held)), timeout=30
                    )
                else:
                    sid = dd.CreateSession(
                        pb.CreateSessionRequest(num_envs=1024), timeout=30
                    )
                held.append(sid.session_id)
                tally.add("memory hog", "OK")
            except grpc.RpcError as e:
                share = "connection" in (e.details() or "")
                tally.add(
                    "memory hog", f"{code_of(e)} ({'share' if share else 'budget'})"
                )
                if share:
                    channel.close()
                    channel, dd = stub(address)
                else:
                    time.sleep(0.01)
    finally:
        channel.close()


def rollout_abuser(address: str, stop: threading.Event, tally: Tally) -> None:
    """Opens Rollout streams it never reads, and others it cancels at once."""
    channel, dd = stub(address)
    unread = []
    try:
        while not stop.is_set():
            request = pb.RolloutRequest(policy=pb.POLICY_EXPERT, seeds=range(10_000))
            stream = dd.Rollout(request, timeout=3600)
            if len(unread) < 8:
                unread.append(stream)
                tally.add("rollout abuser", "unread stream")
            else:
                stream.cancel()
                tally.add("rollout abuser", "cancelled stream")
            time.sleep(0.05)
    finally:
        for s in unread:
            s.cancel()
        channel.close()


def garbler(address: str, stop: threading.Event, tally: Tally) -> None:
    """Sends bytes that do not decode, and snapshots with random bytes changed."""
    channel, dd = stub(address)
    raw = channel.unary_unary("/dinerdash.v1.DinerDash/Step")
    rng = random.Random(7)
    try:
        sid = dd.CreateSession(
            pb.CreateSessionRequest(num_envs=2, seed=3), timeout=30
        ).session_id
        dd.Reset(pb.ResetRequest(session_id=sid), timeout=30)
        snap = dd.Snapshot(pb.SnapshotRequest(session_id=sid), timeout=30).snapshot
        while not stop.is_set():
            try:
                raw(
                    bytes(rng.randrange(256) for _ in range(rng.randrange(1, 64))),
                    timeout=30,
                )
                tally.add("garbler", "garbage OK")
            except grpc.RpcError as e:
                tally.add("garbler", f"garbage {code_of(e)}")
            mangled = bytearray(snap)
            for _ in range(rng.randrange(1, 4)):
                mangled[rng.randrange(6, len(mangled))] = rng.randrange(256)
            try:
                restored = dd.Restore(
                    pb.RestoreRequest(snapshot=bytes(mangled)), timeout=30
                )
                dd.CloseSession(pb.CloseSessionRequest(session_id=restored.session_id))
                tally.add("garbler", "restore OK")
            except grpc.RpcError as e:
                tally.add("garbler", f"restore {code_of(e)}")
            time.sleep(0.002)
    except grpc.RpcError as e:
        tally.add("garbler", f"setup {code_of(e)}")
    finally:
        channel.close()


def silent(address: str, stop: threading.Event, tally: Tally) -> None:
    """Keeps opening TCP connections that never say anything (up to 200 at once)."""
    host, port = address.rsplit(":", 1)
    held: list[socket.socket] = []
    while not stop.is_set():
        held = [s for s in held if not _closed(s)]
        if len(held) < 200:
            try:
                held.append(socket.create_connection((host, int(port)), timeout=5))
                tally.add("silent", "opened")
            except OSError:
                tally.add("silent", "refused")
        time.sleep(0.05)
    for s in held:
        s.close()


def _closed(s: socket.socket) -> bool:
    """Whether the server closed this connection (reads EOF without blocking)."""
    s.setblocking(False)
    try:
        while True:
            data = s.recv(4096)
            if not data:
                s.close()
                return True
    except BlockingIOError:
        return False
    except OSError:
        s.close()
        return True
    finally:
        if s.fileno() != -1:
            s.setblocking(True)


def step_latency(address: str, seconds: float) -> list[float]:
    """Single-environment Step round trips for `seconds`, one after another."""
    channel, dd = stub(address)
    sid = dd.CreateSession(
        pb.CreateSessionRequest(num_envs=1, seed=5), timeout=30
    ).session_id
    dd.Reset(pb.ResetRequest(session_id=sid), timeout=30)
    wait = (0).to_bytes(4, "little")
    out = []
    end = time.monotonic() + seconds
    while time.monotonic() < end:
        started = time.perf_counter()
        batch = dd.Step(pb.StepRequest(session_id=sid, actions=wait), timeout=30)
        out.append(time.perf_counter() - started)
        if batch.terminated != b"\x00" or batch.truncated != b"\x00":
            dd.Reset(pb.ResetRequest(session_id=sid), timeout=30)
    dd.CloseSession(pb.CloseSessionRequest(session_id=sid), timeout=30)
    channel.close()
    return out


def reader(address: str, stop: threading.Event) -> None:
    """Reads expert Rollout episodes as fast as they come until told to stop."""
    channel, dd = stub(address)
    stream = dd.Rollout(pb.RolloutRequest(policy=pb.POLICY_EXPERT, seeds=range(10_000)))
    try:
        for _ in stream:
            if stop.is_set():
                break
    except grpc.RpcError:
        pass
    finally:
        stream.cancel()
        channel.close()


def rollout_latency(address: str, seconds: float) -> None:
    """Prints Step p50/p99 alone, then beside two Rollout streams being read."""

    def summary(xs: list[float]) -> str:
        xs = sorted(xs)
        p99 = xs[min(len(xs) - 1, int(0.99 * len(xs)))]
        return f"{len(xs)} calls, p50 {statistics.median(xs) * 1e3:.2f} ms, p99 {p99 * 1e3:.2f} ms"

    print(f"Step alone: {summary(step_latency(address, seconds))}", flush=True)
    stop = threading.Event()
    readers = [threading.Thread(target=reader, args=(address, stop)) for _ in range(2)]
    for t in readers:
        t.start()
    time.sleep(1)
    print(
        f"Step beside two Rollouts read: {summary(step_latency(address, seconds))}",
        flush=True,
    )
    stop.set()
    for t in readers:
        t.join(timeout=60)


def rss_per_env(address: str, pid: int) -> None:
    """Prints the server's RSS growth for 100 reset sessions of 1024 environments beside what
    the memory budget counts for them (two connections: one's share is 65,536 environments)."""
    stubs = [stub(address) for _ in range(2)]
    stubs[0][1].ServerInfo(pb.ServerInfoRequest(), timeout=30)
    time.sleep(0.5)
    before = rss_mib(pid)
    for i in range(100):
        dd = stubs[i % 2][1]
        sid = dd.CreateSession(
            pb.CreateSessionRequest(num_envs=1024, seed=i), timeout=30
        )
        dd.Reset(pb.ResetRequest(session_id=sid.session_id), timeout=30)
    time.sleep(0.5)
    grown = rss_mib(pid) - before
    counted = (
        stubs[0][1].ServerInfo(pb.ServerInfoRequest(), timeout=30).memory_used_bytes
    )
    envs = 100 * 1024
    per_env = grown * 2**20 / envs
    print(
        f"100 sessions of 1024 environments: RSS +{grown:.1f} MiB ({per_env:.0f} B an env);"
    )
    print(
        f"the budget counts {counted / 2**20:.1f} MiB ({counted / envs:.0f} B an env)"
    )
    for channel, _ in stubs:
        channel.close()


def rss_mib(pid: int) -> float:
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1]) / 1024
    return 0.0


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument(
        "--duration", type=float, default=600, help="seconds (default 600)"
    )
    parser.add_argument("--trainers", type=int, default=4)
    parser.add_argument(
        "--address", help="an already running server; default: start one"
    )
    parser.add_argument(
        "--server", default=str(ROOT / "target/release/dinerdash-server")
    )
    parser.add_argument(
        "--rollout-latency",
        action="store_true",
        help="instead: Step p50/p99 alone and beside two Rollouts being read (--duration each)",
    )
    parser.add_argument(
        "--rss-per-env",
        action="store_true",
        help="instead: RSS growth per environment beside the budget's count (starts a server)",
    )
    args = parser.parse_args()

    proc = None
    address = args.address
    if address is None:
        proc = subprocess.Popen(
            [args.server, "--port", "0", "--log-format", "json"],
            stdout=subprocess.PIPE,
            stderr=subprocess.DEVNULL,
            text=True,
        )
        line = proc.stdout.readline()
        address = line.strip().rsplit(" ", 1)[-1]
    if args.rss_per_env and proc is not None:
        try:
            rss_per_env(address, proc.pid)
        finally:
            proc.terminate()
            proc.wait(timeout=60)
        return 0
    if args.rollout_latency:
        try:
            rollout_latency(address, args.duration)
        finally:
            if proc is not None:
                proc.terminate()
                proc.wait(timeout=60)
        return 0
    print(f"soak: {args.duration:.0f} s against {address}", flush=True)

    stop = threading.Event()
    tally = Tally()
    latencies: list[list[float]] = [[] for _ in range(args.trainers)]
    threads = [
        threading.Thread(target=trainer, args=(address, stop, tally, latencies[i]))
        for i in range(args.trainers)
    ]
    for hostile in (memory_hog, memory_hog, rollout_abuser, garbler, silent):
        threads.append(threading.Thread(target=hostile, args=(address, stop, tally)))
    for t in threads:
        t.start()

    peak = 0.0
    started = time.monotonic()
    alive = True
    try:
        while time.monotonic() - started < args.duration:
            time.sleep(min(5.0, max(0.0, args.duration - (time.monotonic() - started))))
            if proc is not None:
                if proc.poll() is not None:
                    alive = False
                    break
                peak = max(peak, rss_mib(proc.pid))
    finally:
        stop.set()
        for t in threads:
            t.join(timeout=60)
        info = None
        try:
            channel, dd = stub(address)
            info = dd.ServerInfo(pb.ServerInfoRequest(), timeout=30)
            channel.close()
        except grpc.RpcError:
            pass
        if proc is not None:
            if proc.poll() is None:
                peak = max(peak, rss_mib(proc.pid))
                proc.terminate()
            proc.wait(timeout=60)

    steps = sorted(x for per in latencies for x in per)
    print(f"server alive: {alive}")
    if proc is not None:
        print(f"server peak RSS: {peak:.0f} MiB")
    if info is not None:
        used, budget = info.memory_used_bytes >> 20, info.max_memory_bytes >> 20
        print(f"memory budget: {used} of {budget} MiB held at the end")
    if steps:
        p50 = statistics.median(steps) * 1e3
        p99 = steps[min(len(steps) - 1, int(0.99 * len(steps)))] * 1e3
        print(
            f"trainer Step (64 envs): {len(steps)} calls, p50 {p50:.2f} ms, p99 {p99:.2f} ms"
        )
    trainer_errors = sum(
        n
        for (who, what), n in tally.counts.items()
        if who == "trainer" and what != "steps"
    )
    lost = tally.counts[("trainer", "session lost")]
    print(f"trainer errors: {trainer_errors}, sessions lost: {lost}")
    for (who, what), n in sorted(tally.counts.items()):
        if who != "trainer":
            print(f"  {who}: {what} x {n}")
    return 0 if alive and trainer_errors == 0 else 1


if __name__ == "__main__":
    sys.exit(main())

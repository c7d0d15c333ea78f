"""Retries of ``UNAVAILABLE`` by the channel's service config (issue 37, item 5): a retryable
refusal is retried by gRPC's ``retryPolicy`` itself, a Step never is, and a draining server, whose
refusal carries the retry push-back ``grpc-retry-pushback-ms: -1``, is asked exactly once however
many retries the connection has (counted by the server's own metrics)."""

from __future__ import annotations

import json
import re
import socket
import struct
import threading
import time
import urllib.request

import grpc
import pytest
from dinerdash import Connection, ServerDraining, ServiceTransportError
from dinerdash._proto import pb
from dinerdash.connection import (
    CHANNEL_MAX_RETRIES,
    NOT_RETRIED,
    RETRY_PUSHBACK,
    SERVICE,
    service_config,
)

from .test_drain import _drain

#: Longest a test waits for something that happens at once on an idle machine.
PATIENCE_S = 30.0

_UNAVAILABLE = re.compile(r'^dinerdash_rpc_errors_total\{code="UNAVAILABLE"\} (\d+)$', re.M)


def _refused(http_port: int) -> int:
    """The server's count of calls it answered UNAVAILABLE (its ``/metrics``)."""
    with urllib.request.urlopen(f"http://127.0.0.1:{http_port}/metrics", timeout=10) as reply:
        text = reply.read().decode()
    match = _UNAVAILABLE.search(text)
    return int(match.group(1)) if match else 0


def test_a_draining_server_is_asked_once_despite_retries(start_server) -> None:
    server = start_server("--drain-timeout", "600", "--http-port", "0")
    conn = Connection(server.address, retries=0)
    eager = Connection(server.address, retries=4, retry_backoff=0.05)
    try:
        http_port = conn.server_info().http_port
        held = conn.call("CreateSession", pb.CreateSessionRequest(num_envs=1))
        _drain(server, conn)
        before = _refused(http_port)
        request = pb.CreateSessionRequest(num_envs=1)

        # Through the channel alone (the raw stub: no retry of the client's own): one attempt,
        # and the push-back that stopped the channel is on the refusal.
        with pytest.raises(grpc.RpcError) as raw:
            eager.stub.CreateSession(request, timeout=PATIENCE_S)
        assert raw.value.code() == grpc.StatusCode.UNAVAILABLE
        assert dict(raw.value.trailing_metadata())[RETRY_PUSHBACK] == "-1"
        assert _refused(http_port) == before + 1

        # As the client calls: typed, and still once.
        with pytest.raises(ServerDraining, match="asked not to be retried"):
            eager.call("CreateSession", request)
        assert _refused(http_port) == before + 2
        # Beyond the channel's retries (the fallback) the push-back is honoured too.
        with pytest.raises(ServerDraining):
            eager.call("CreateSession", request, retries=10)
        assert _refused(http_port) == before + 3
        # And for a Rollout, opened again by the fallback rather than the channel.
        rollout = pb.RolloutRequest(policy=pb.POLICY_RANDOM, seeds=[1])
        with pytest.raises(ServerDraining):
            list(eager.stream("Rollout", rollout))
        assert _refused(http_port) == before + 4

        conn.call("CloseSession", pb.CloseSessionRequest(session_id=held.session_id))
    finally:
        conn.close()
        eager.close()


class _Refuser:
    """Listens on 127.0.0.1 and resets every connection it accepts, counting them: a port where a
    server is about to be (re)started."""

    def __init__(self) -> None:
        self.sock = socket.socket()
        self.sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        self.sock.bind(("127.0.0.1", 0))
        self.sock.listen(16)
        self.port = self.sock.getsockname()[1]
        self.accepted = threading.Semaphore(0)
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()

    def _run(self) -> None:
        while True:
            try:
                client, _ = self.sock.accept()
            except OSError:  # closed
                return
            client.setsockopt(socket.SOL_SOCKET, socket.SO_LINGER, struct.pack("ii", 1, 0))
            client.close()
            self.accepted.release()

    def close(self) -> None:
        try:
            self.sock.shutdown(socket.SHUT_RDWR)
        except OSError:
            pass
        self.sock.close()
        self._thread.join(PATIENCE_S)


def test_the_channel_retries_unavailable_until_the_server_is_there(start_server) -> None:
    refuser = _Refuser()
    address = f"127.0.0.1:{refuser.port}"
    try:
        # Without retries the refusal is the answer; a Step is never retried.
        with Connection(address, wait=False, retries=0) as once:
            with pytest.raises(ServiceTransportError, match="after 1 attempt"):
                once.call("ServerInfo", pb.ServerInfoRequest())
            # The fallback: more retries than the channel makes (none here), counted exactly.
            with pytest.raises(ServiceTransportError, match="after 3 attempts"):
                once.call("ServerInfo", pb.ServerInfoRequest(), retries=2)
        with Connection(address, wait=False, retries=4, retry_backoff=0.01) as stepper:
            with pytest.raises(ServiceTransportError, match=r"Step: .* after 1 attempt"):
                stepper.call("Step", pb.StepRequest(session_id="x"), timeout=PATIENCE_S)
            # Beyond gRPC's five attempts: the channel's call once more, whole.
            with pytest.raises(ServiceTransportError, match="after up to 10 attempts"):
                stepper.call("ServerInfo", pb.ServerInfoRequest(), retries=5, timeout=PATIENCE_S)
        while refuser.accepted.acquire(blocking=False):
            pass

        # With a backoff of 2 s the channel's four retries come about 2, 6, 14 and 30 s after
        # the first attempt (gRPC jitters them by a fifth): the server has long started by the
        # last. The raw stub (no retry of the client's own) on the retrying channel: its first
        # attempt is refused...
        with Connection(address, wait=False, retries=4, retry_backoff=2.0) as eager:
            future = eager.stub.ServerInfo.future(pb.ServerInfoRequest(), timeout=120)
            # A request above gRPC's default retry buffer (256 KiB) is retried as well.
            big = eager.stub.Restore.future(pb.RestoreRequest(snapshot=bytes(1 << 20)), timeout=120)
            assert refuser.accepted.acquire(timeout=PATIENCE_S), "the call never reached the port"
            # ... then the server starts on that port, and a retry of the channel reaches it.
            refuser.close()
            deadline = time.monotonic() + PATIENCE_S
            while True:
                try:
                    start_server(port=refuser.port)
                    break
                except pytest.fail.Exception:
                    assert time.monotonic() < deadline, "the port never came free"
                    time.sleep(0.1)
            assert future.result(timeout=120).server_version
            with pytest.raises(grpc.RpcError) as refused:
                big.result(timeout=120)
            assert refused.value.code() == grpc.StatusCode.INVALID_ARGUMENT  # the server read it
    finally:
        refuser.close()


def test_the_service_config_retries_unavailable_of_all_but_the_not_retried() -> None:
    config = json.loads(service_config(10, 0.25))
    default, excluded = config["methodConfig"]
    assert default["name"] == [{"service": SERVICE}]
    assert default["retryPolicy"] == {
        "maxAttempts": CHANNEL_MAX_RETRIES + 1,  # gRPC's cap; the fallback makes the rest
        "initialBackoff": "0.250000000s",
        "maxBackoff": "2.000000000s",
        "backoffMultiplier": 2,
        "retryableStatusCodes": ["UNAVAILABLE"],
    }
    methods = {name["method"] for name in excluded["name"]}
    assert NOT_RETRIED <= methods and "retryPolicy" not in excluded
    assert json.loads(service_config(2, 0.1))["methodConfig"][0]["retryPolicy"]["maxAttempts"] == 3
    assert json.loads(service_config(0, 0.1)) == {"methodConfig": []}
    with pytest.raises(ValueError, match="retries"):
        Connection("127.0.0.1:1", wait=False, retries=-1)
    with pytest.raises(ValueError, match="retry_backoff"):
        Connection("127.0.0.1:1", wait=False, retry_backoff=float("nan"))

"""TLS end to end, with certificates made at test time: a private CA (``tls_ca=``,
``DINERDASH_TLS_CA``, ``--tls-ca`` of the CLI), a self-signed certificate that is its own CA
(also for ``dinerdash-server health --tls-ca``), the errors that say TLS when client and server
disagree, and the web endpoint served over TLS with the same certificate (its ``Host`` check
too)."""

from __future__ import annotations

import datetime
import http.client
import ipaddress
import ssl
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest
from dinerdash import Connection, DinerDashEnv, DinerDashVectorEnv, TLSMismatch
from dinerdash.watch import pages_url

from .conftest import ServerProcess, server_binary, server_env

x509 = pytest.importorskip("cryptography.x509", reason="the dev extra brings cryptography")
from cryptography.hazmat.primitives import hashes, serialization  # noqa: E402
from cryptography.hazmat.primitives.asymmetric import ec  # noqa: E402
from cryptography.x509.oid import NameOID  # noqa: E402

_NAMES = [x509.DNSName("localhost"), x509.IPAddress(ipaddress.ip_address("127.0.0.1"))]


def _key() -> ec.EllipticCurvePrivateKey:
    return ec.generate_private_key(ec.SECP256R1())


def _pem(cert: x509.Certificate) -> bytes:
    return cert.public_bytes(serialization.Encoding.PEM)


def _key_pem(key: ec.EllipticCurvePrivateKey) -> bytes:
    return key.private_bytes(
        serialization.Encoding.PEM,
        serialization.PrivateFormat.PKCS8,
        serialization.NoEncryption(),
    )


def _certificate(
    subject: str,
    key: ec.EllipticCurvePrivateKey,
    issuer: str,
    issuer_key: ec.EllipticCurvePrivateKey,
    *,
    ca: bool,
    names: bool,
) -> x509.Certificate:
    now = datetime.datetime.now(datetime.timezone.utc)
    builder = (
        x509.CertificateBuilder()
        .subject_name(x509.Name([x509.NameAttribute(NameOID.COMMON_NAME, subject)]))
        .issuer_name(x509.Name([x509.NameAttribute(NameOID.COMMON_NAME, issuer)]))
        .public_key(key.public_key())
        .serial_number(x509.random_serial_number())
        .not_valid_before(now - datetime.timedelta(minutes=5))
        .not_valid_after(now + datetime.timedelta(days=1))
        .add_extension(x509.BasicConstraints(ca=ca, path_length=None), critical=True)
    )
    if names:
        builder = builder.add_extension(x509.SubjectAlternativeName(_NAMES), critical=False)
    return builder.sign(issuer_key, hashes.SHA256())


@pytest.fixture(scope="module")
def pki(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    """A private CA and a server certificate it signed; a self-signed certificate that is its own
    CA (as ``openssl req -x509`` makes); and an unrelated CA."""
    out = tmp_path_factory.mktemp("pki")
    files: dict[str, Path] = {}

    def write(name: str, data: bytes) -> None:
        files[name] = out / name
        files[name].write_bytes(data)

    ca_key, server_key, self_key, other_key = _key(), _key(), _key(), _key()
    ca = _certificate("test CA", ca_key, "test CA", ca_key, ca=True, names=False)
    server = _certificate("localhost", server_key, "test CA", ca_key, ca=False, names=True)
    selfsigned = _certificate("localhost", self_key, "localhost", self_key, ca=True, names=True)
    other = _certificate("other CA", other_key, "other CA", other_key, ca=True, names=False)
    write("ca.pem", _pem(ca))
    write("server.pem", _pem(server))
    write("server.key", _key_pem(server_key))
    write("self.pem", _pem(selfsigned))
    write("self.key", _key_pem(self_key))
    write("other-ca.pem", _pem(other))
    return files


@pytest.fixture(scope="module")
def tls_server(pki: dict[str, Path]) -> Iterator[ServerProcess]:
    """A server whose certificate the private CA signed."""
    server = ServerProcess(
        "--tls-cert", str(pki["server.pem"]), "--tls-key", str(pki["server.key"])
    )
    yield server
    server.stop()


@pytest.fixture(scope="module")
def self_signed_server(pki: dict[str, Path]) -> Iterator[ServerProcess]:
    server = ServerProcess("--tls-cert", str(pki["self.pem"]), "--tls-key", str(pki["self.key"]))
    yield server
    server.stop()


def _play(env: DinerDashEnv) -> None:
    _, info = env.reset(seed=3)
    for _ in range(20):
        _, _, terminated, truncated, info = env.step(int(np.flatnonzero(info["action_mask"])[-1]))
        assert not (terminated or truncated)
    assert info["tick"] == 20


def test_a_private_ca_by_keyword_and_by_environment(
    tls_server: ServerProcess, pki: dict[str, Path], monkeypatch: pytest.MonkeyPatch
) -> None:
    env = DinerDashEnv(tls_server.address, tls_ca=pki["ca.pem"])
    try:
        _play(env)
    finally:
        env.close()
    monkeypatch.setenv("DINERDASH_TLS_CA", str(pki["ca.pem"]))
    envs = DinerDashVectorEnv(3, tls_server.address)
    try:
        _, info = envs.reset(seed=0)
        _, _, _, _, info = envs.step(np.zeros(3, dtype=np.int64))
        np.testing.assert_array_equal(info["tick"], [1, 1, 1])
    finally:
        envs.close()


def test_a_self_signed_certificate_is_its_own_ca(
    self_signed_server: ServerProcess, pki: dict[str, Path]
) -> None:
    env = DinerDashEnv(self_signed_server.address, tls_ca=str(pki["self.pem"]))
    try:
        _play(env)
    finally:
        env.close()


def test_plaintext_against_tls_says_tls(tls_server: ServerProcess) -> None:
    # Said at once, not after the connect timeout: the server answers, just not in plaintext.
    with pytest.raises(TLSMismatch, match="speaks TLS") as e:
        DinerDashEnv(tls_server.address, connect_timeout=60)
    assert "tls_ca" in str(e.value) and e.value.address == tls_server.address


def test_tls_against_plaintext_and_an_untrusted_certificate_say_tls(
    address: str, tls_server: ServerProcess, pki: dict[str, Path]
) -> None:
    with pytest.raises(TLSMismatch, match="does not speak TLS"):
        DinerDashVectorEnv(2, address, tls_ca=pki["ca.pem"], connect_timeout=60)
    with pytest.raises(TLSMismatch, match="not trusted"):
        DinerDashEnv(tls_server.address, tls_ca=pki["other-ca.pem"], connect_timeout=2)
    # tls=True trusts the system's roots, which never signed a test certificate.
    with pytest.raises(TLSMismatch, match="not trusted"):
        DinerDashEnv(tls_server.address, tls=True, connect_timeout=2)


def test_the_cli_connects_with_tls_ca(tls_server: ServerProcess, pki: dict[str, Path]) -> None:
    cmd = [sys.executable, "-m", "dinerdash", "evaluate", "--policy", "expert", "--episodes", "2"]
    cmd += ["--max-steps", "50", "--address", tls_server.address, "--tls-ca", str(pki["ca.pem"])]
    done = subprocess.run(cmd, capture_output=True, text=True, timeout=120, env=server_env())
    assert done.returncode == 0, done.stderr
    assert "policy expert: 2 episodes" in done.stdout


@pytest.mark.parametrize("which", ["tls_server", "self_signed_server"])
def test_server_health_with_tls_ca(which: str, pki: dict[str, Path], request) -> None:
    """The Docker HEALTHCHECK's probe over TLS, trusting the private CA or the self-signed
    certificate itself."""
    server = request.getfixturevalue(which)
    ca = pki["ca.pem"] if which == "tls_server" else pki["self.pem"]
    cmd = [str(server_binary()), "health", "--address", f"localhost:{server.port}"]
    done = subprocess.run(
        [*cmd, "--tls-ca", str(ca), "--timeout", "10"],
        capture_output=True,
        text=True,
        timeout=60,
        env=server_env(),
    )
    assert done.returncode == 0, done.stdout + done.stderr
    assert done.stdout.strip() == "SERVING"


#: The web endpoint's test token (16 characters or more, no ``#``).
_TOKEN = "web-endpoint-token-0123456789"


def _get(conn: http.client.HTTPConnection, host: str | None = None) -> tuple[int, str]:
    headers = {"Authorization": f"Bearer {_TOKEN}"}
    if host is not None:
        headers["Host"] = host
    try:
        conn.request("GET", "/api/sessions", headers=headers)
        reply = conn.getresponse()
        return reply.status, reply.read().decode()
    finally:
        conn.close()


def test_the_web_endpoint_serves_tls_with_the_same_certificate(pki: dict[str, Path]) -> None:
    server = ServerProcess(
        "--tls-cert",
        str(pki["server.pem"]),
        "--tls-key",
        str(pki["server.key"]),
        "--http-port",
        "0",
        "--auth-token",
        _TOKEN,
    )
    try:
        with Connection(server.address, tls_ca=pki["ca.pem"], token=_TOKEN) as conn:
            port = conn.server_info().http_port
            # The client knows the pages are HTTPS, as its own channel is TLS.
            assert pages_url(conn) == f"https://127.0.0.1:{port}/"
        context = ssl.create_default_context(cafile=str(pki["ca.pem"]))
        status, body = _get(http.client.HTTPSConnection("localhost", port, context=context))
        assert status == 200 and '"sessions"' in body
        # A host name the endpoint does not serve (a DNS name rebound to it): 421.
        https = http.client.HTTPSConnection("localhost", port, context=context)
        status, body = _get(https, host="rebound.example.com")
        assert status == 421 and "--http-allowed-host" in body
        # Plain HTTP gets no HTTP answer: the token never crosses the network in clear.
        with pytest.raises((http.client.HTTPException, OSError)):
            _get(http.client.HTTPConnection("127.0.0.1", port, timeout=30))
    finally:
        server.stop()

"""The deployment files are safe when exposed: ``docker/Dockerfile``, ``docker/compose.yaml`` and
``docker/k8s/dinerdash.yaml`` start the server on every address (``--host 0.0.0.0``) only with a
token taken from a secret (an env file, a Kubernetes Secret), never on the command line and never
with ``--insecure``; the compose trainer gets the same token. Compose and Kubernetes serve TLS
with a certificate and key from secrets (Compose secrets, a ``kubernetes.io/tls`` Secret); every
file's health checks ask the probe port (``--probe-port``: health alone, plaintext, no token; the
Docker HEALTHCHECK, which compose keeps, and the kubelet's gRPC probes); every container drops
all capabilities, cannot gain privileges, runs under the runtime's default seccomp profile on a
read-only root file system, and a NetworkPolicy admits only the trainers' pods, only to the gRPC
port. The base images are build
arguments, pinned by digest only where a real digest is known (none is here: see the
Dockerfile's comment). Then the real binary, started with the very arguments each file gives:
without the token it refuses to start (before it binds anything), and with it (moved to
127.0.0.1 and free ports, the secrets' files replaced by a certificate made like the Makefile's)
a client without the token is refused, and one with it and the certificate is served over TLS;
the files' own health checks pass against its probe port, and a health check of its gRPC port
without the token is refused.

This stands in for ``make docker-smoke`` and ``make k8s-validate`` where no Docker engine or
cluster runs (CI)."""

from __future__ import annotations

import json
import re
import secrets
import shutil
import subprocess
from pathlib import Path

import pytest
from dinerdash import Connection, Unauthenticated
from dinerdash.server import LocalServer

from .conftest import REPO, server_binary, server_env

yaml = pytest.importorskip("yaml", reason="PyYAML reads the compose file and the manifest")

DOCKER = REPO / "docker"
TOKEN_VARIABLE = "DINERDASH_AUTH_TOKEN"
SERVERS = ("server1", "server2", "server3")


def _dockerfile_args() -> list[str]:
    """The server image's CMD (the last stage's, the image's default)."""
    lines = (DOCKER / "Dockerfile").read_text().splitlines()
    cmds = [line for line in lines if line.startswith("CMD [")]
    return json.loads(cmds[-1].removeprefix("CMD "))


def _compose() -> dict:
    return yaml.safe_load((DOCKER / "compose.yaml").read_text())


def _k8s_docs() -> list[dict]:
    return list(yaml.safe_load_all((DOCKER / "k8s" / "dinerdash.yaml").read_text()))


def _k8s_pod() -> dict:
    (deployment,) = [d for d in _k8s_docs() if d["kind"] == "Deployment"]
    return deployment["spec"]["template"]


def _k8s_container() -> dict:
    (container,) = _k8s_pod()["spec"]["containers"]
    return container


def _shipped_args() -> dict[str, list[str]]:
    return {
        "Dockerfile": _dockerfile_args(),
        "compose": _compose()["services"]["server1"]["command"],
        "k8s": _k8s_container()["args"],
    }


def _value(args: list[str], flag: str) -> str | None:
    return args[args.index(flag) + 1] if flag in args else None


def _no_secret_on_the_command_line(args: list[str]) -> None:
    assert "--auth-token" not in args, "a token on the command line shows in ps"
    assert "--insecure" not in args


def test_the_image_binds_every_address_and_holds_no_token() -> None:
    args = _dockerfile_args()
    assert _value(args, "--host") == "0.0.0.0"
    _no_secret_on_the_command_line(args)
    for line in (DOCKER / "Dockerfile").read_text().splitlines():
        if line.startswith(("ENV", "ARG")):
            assert TOKEN_VARIABLE not in line, line


def test_compose_gives_servers_and_trainer_the_token_from_an_env_file() -> None:
    services = _compose()["services"]
    for name in (*SERVERS, "trainer"):
        service = services[name]
        assert service.get("env_file") == ["dinerdash.env"], name
        assert TOKEN_VARIABLE not in (service.get("environment") or {}), name
    for name in SERVERS:
        assert _value(services[name]["command"], "--host") == "0.0.0.0"
        _no_secret_on_the_command_line(services[name]["command"])
    # The env file is a secret made per machine, never committed.
    assert "/docker/dinerdash.env" in (REPO / ".gitignore").read_text().splitlines()
    makefile = (REPO / "Makefile").read_text()
    assert "docker-smoke: docker/dinerdash.env" in makefile
    assert "openssl rand -hex 32" in makefile


def test_the_manifest_takes_the_token_from_a_secret() -> None:
    container = _k8s_container()
    assert _value(container["args"], "--host") == "0.0.0.0"
    _no_secret_on_the_command_line(container["args"])
    (token,) = [e for e in container["env"] if e["name"] == TOKEN_VARIABLE]
    assert "value" not in token, "the token must come from a Secret, not the manifest"
    assert token["valueFrom"]["secretKeyRef"] == {"name": "dinerdash-auth", "key": "token"}
    docs = list(yaml.safe_load_all((DOCKER / "k8s" / "dinerdash.yaml").read_text()))
    assert not [d for d in docs if d["kind"] == "Secret"], "the Secret is made apart"


@pytest.mark.parametrize("source", ["Dockerfile", "compose", "k8s"])
def test_without_the_token_the_shipped_arguments_do_not_start(source: str, tmp_path: Path) -> None:
    args = _with_tls_files(_shipped_args()[source], *_makefile_certificate(tmp_path))
    done = subprocess.run(
        [str(server_binary()), *args],
        capture_output=True,
        text=True,
        timeout=60,
        env=server_env(),  # no DINERDASH_AUTH_TOKEN
    )
    assert done.returncode != 0
    assert "listening" not in done.stdout  # refused before binding 0.0.0.0
    assert TOKEN_VARIABLE in done.stderr and "--insecure" in done.stderr, done.stderr


def _replaced(args: list[str], values: dict[str, str | None]) -> list[str]:
    """``args``, each flag of ``values`` given that value, or left out with its value (None)."""
    out: list[str] = []
    skip = False
    for arg in args:
        if skip:
            skip = False
        elif arg in values:
            if values[arg] is not None:
                out += [arg, values[arg]]
            skip = True
        else:
            out.append(arg)
    return out


def _with_tls_files(args: list[str], cert: Path, key: Path) -> list[str]:
    """``args``, the TLS files (the secrets' paths in the container) ``cert`` and ``key``."""
    return _replaced(args, {"--tls-cert": str(cert), "--tls-key": str(key)})


def _on_loopback(args: list[str], cert: Path, key: Path) -> list[str]:
    """``args`` without ``--host``/``--port`` (LocalServer gives 127.0.0.1 and port 0), the
    metrics and probe ports free ones, the TLS files ``cert`` and ``key``."""
    free = {"--host": None, "--port": None, "--metrics-port": "0", "--probe-port": "0"}
    loopback = _replaced(args, free)
    return _with_tls_files(loopback, cert, key)


def _makefile_certificate(folder: Path) -> tuple[Path, Path]:
    """A certificate and key made by the Makefile's own recipe (``docker/tls/server.crt``), its
    paths rewritten into ``folder``."""
    if shutil.which("openssl") is None:
        pytest.skip("openssl makes the compose file's certificate")
    makefile = (REPO / "Makefile").read_text()
    recipe = makefile.split("docker/tls/server.crt:\n", 1)[1].split("\n\n", 1)[0]
    script = recipe.replace("\t", "").replace("$@", "docker/tls/server.crt")
    script = script.replace("docker/tls", str(folder / "tls"))
    subprocess.run(["sh", "-ec", script], check=True, capture_output=True, timeout=60)
    return folder / "tls" / "server.crt", folder / "tls" / "server.key"


@pytest.mark.parametrize("source", ["Dockerfile", "compose", "k8s"])
def test_with_the_token_a_client_without_it_is_refused(
    source: str, monkeypatch: pytest.MonkeyPatch, tmp_path: Path
) -> None:
    token = secrets.token_hex(32)
    cert, key = _makefile_certificate(tmp_path)
    args = _shipped_args()[source]
    tls = "--tls-cert" in args
    # The files that serve TLS also check health over it.
    assert tls == (source != "Dockerfile")
    monkeypatch.setenv(TOKEN_VARIABLE, token)  # as the env file or the Secret sets it
    with LocalServer(server_binary(), args=_on_loopback(args, cert, key)) as server:
        monkeypatch.delenv(TOKEN_VARIABLE)
        ca = {"tls_ca": str(cert)} if tls else {}
        with pytest.raises(Unauthenticated):
            with Connection(server.address, **ca) as conn:
                conn.server_info()
        with pytest.raises(Unauthenticated):
            with Connection(server.address, token="not-the-token-0123456789", **ca) as conn:
                conn.server_info()
        with Connection(server.address, token=token, **ca) as conn:
            assert conn.server_info().live_sessions == 0
            # The client's own health Check (failover, membership) sends the token.
            assert conn.health(60).result() is True
        # The health checks the file gives, against this server's probe port.
        assert server.probe_address is not None
        for check in _health_checks(source):
            check[check.index("--address") + 1] = server.probe_address
            done = _health(check)
            assert done.returncode == 0 and done.stdout.strip() == "SERVING", done
        # The gRPC port answers health only to callers with the token.
        tls_ca = ["--tls-ca", str(cert)] if tls else []
        done = _health(["--address", server.address, *tls_ca])
        assert done.returncode != 0 and "Unauthenticated" in done.stderr, done


def _health(args: list[str]) -> subprocess.CompletedProcess:
    """``dinerdash-server health`` with ``args``."""
    return subprocess.run(
        [str(server_binary()), "health", *args], capture_output=True, text=True, timeout=60
    )


def _health_checks(source: str) -> list[list[str]]:
    """The arguments of ``dinerdash-server health`` that ask what the file's health checks ask:
    the image's HEALTHCHECK (compose keeps it), or what the kubelet's gRPC probes ask (a Check
    of the probe's service, plaintext, on its port of the pod)."""
    if source in ("Dockerfile", "compose"):
        return [_dockerfile_healthcheck()[2:]]
    container = _k8s_container()
    checks = []
    for probe in ("readinessProbe", "livenessProbe"):
        grpc = container[probe]["grpc"]
        address = f"127.0.0.1:{grpc['port']}"
        checks.append(["--address", address, "--service", grpc.get("service", "")])
    return checks


def _dockerfile_healthcheck() -> list[str]:
    """The image's HEALTHCHECK command."""
    text = (DOCKER / "Dockerfile").read_text()
    command = text.split("HEALTHCHECK ", 1)[1].split(" CMD ", 1)[1].split("\n", 1)[0]
    return json.loads(command)


def test_compose_and_kubernetes_serve_tls_from_secrets() -> None:
    compose = _compose()
    assert compose["secrets"] == {
        "dinerdash_tls_cert": {"file": "./tls/server.crt"},
        "dinerdash_tls_key": {"file": "./tls/server.key"},
    }
    assert "/docker/tls/" in (REPO / ".gitignore").read_text().splitlines()
    assert (
        "docker-smoke: docker/dinerdash.env docker/tls/server.crt"
        in (REPO / "Makefile").read_text()
    )
    for name in SERVERS:
        service = compose["services"][name]
        assert service["secrets"] == ["dinerdash_tls_cert", "dinerdash_tls_key"]
        command = service["command"]
        assert _value(command, "--tls-cert") == "/run/secrets/dinerdash_tls_cert"
        assert _value(command, "--tls-key") == "/run/secrets/dinerdash_tls_key"
    trainer = compose["services"]["trainer"]
    assert trainer["secrets"] == ["dinerdash_tls_cert"]
    assert trainer["environment"]["DINERDASH_TLS_CA"] == "/run/secrets/dinerdash_tls_cert"
    # The trainer dials names the Makefile's certificate holds.
    names = re.search(r"subjectAltName=([^\"]+)", (REPO / "Makefile").read_text()).group(1)
    for address in trainer["environment"]["DINERDASH_ADDRESS"].split(","):
        assert f"DNS:{address.rsplit(':', 1)[0]}" in names.split(","), address

    pod = _k8s_pod()["spec"]
    container = _k8s_container()
    (volume,) = [v for v in pod["volumes"] if v["name"] == "tls"]
    assert volume["secret"]["secretName"] == "dinerdash-tls"
    (mount,) = [m for m in container["volumeMounts"] if m["name"] == "tls"]
    assert mount["readOnly"] is True
    directory = mount["mountPath"]
    assert _value(container["args"], "--tls-cert") == f"{directory}/tls.crt"
    assert _value(container["args"], "--tls-key") == f"{directory}/tls.key"


def test_every_health_check_asks_the_probe_port() -> None:
    """The probe port (health alone, plaintext, no token) is what the Docker HEALTHCHECK, the
    compose servers (which keep the image's check) and the kubelet's gRPC probes ask; the gRPC
    port then asks a token of health checks too."""
    port = _value(_dockerfile_args(), "--probe-port")
    assert port is not None and port != _value(_dockerfile_args(), "--port")
    assert _dockerfile_healthcheck() == [
        "dinerdash-server",
        "health",
        "--address",
        f"127.0.0.1:{port}",
    ]
    expose = [line for line in (DOCKER / "Dockerfile").read_text().splitlines() if "EXPOSE" in line]
    assert port in expose[0].split(), expose
    for name in SERVERS:
        service = _compose()["services"][name]
        assert _value(service["command"], "--probe-port") == port, name
        assert "healthcheck" not in service, f"{name}: the image's HEALTHCHECK asks the probe port"
    container = _k8s_container()
    assert _value(container["args"], "--probe-port") == port
    (probe,) = [p for p in container["ports"] if p["name"] == "probe"]
    assert probe["containerPort"] == int(port)
    # The kubelet's own gRPC probes (they name a port by number), plaintext as the port is.
    assert container["readinessProbe"]["grpc"] == {"port": int(port)}
    assert container["livenessProbe"]["grpc"] == {"port": int(port), "service": "liveness"}
    for probe in ("readinessProbe", "livenessProbe"):
        assert "exec" not in container[probe], probe
    # The NetworkPolicy admits no pod to the probe port (the test below: the trainers to the
    # gRPC port alone); the kubelet's probes come from the node, which it does not filter in
    # most network plugins, as the manifest says.
    text = (DOCKER / "k8s" / "dinerdash.yaml").read_text()
    assert "not subject to NetworkPolicy" in text


def test_every_container_is_confined() -> None:
    services = _compose()["services"]
    for name in (*SERVERS, "trainer"):
        service = services[name]
        assert service["cap_drop"] == ["ALL"], name
        assert "no-new-privileges:true" in service["security_opt"], name
        # Docker's default seccomp profile applies unless a service turns it off.
        assert not [o for o in service["security_opt"] if o.startswith("seccomp")], name
        assert service["read_only"] is True, name
        assert "privileged" not in service and "cap_add" not in service, name
    pod = _k8s_pod()["spec"]
    assert pod["securityContext"]["runAsNonRoot"] is True
    assert pod["securityContext"]["seccompProfile"] == {"type": "RuntimeDefault"}
    assert pod["automountServiceAccountToken"] is False
    context = _k8s_container()["securityContext"]
    assert context["capabilities"] == {"drop": ["ALL"]}
    assert context["allowPrivilegeEscalation"] is False
    assert context["readOnlyRootFilesystem"] is True
    assert context["seccompProfile"] == {"type": "RuntimeDefault"}


def test_a_network_policy_admits_only_the_trainers_to_the_grpc_port() -> None:
    (policy,) = [d for d in _k8s_docs() if d["kind"] == "NetworkPolicy"]
    spec = policy["spec"]
    assert spec["podSelector"]["matchLabels"] == _k8s_pod()["metadata"]["labels"]
    assert spec["policyTypes"] == ["Ingress"]
    (rule,) = spec["ingress"]
    # One peer: pods with the trainers' label (no namespace or address block beside it).
    assert rule["from"] == [{"podSelector": {"matchLabels": {"dinerdash-client": "true"}}}]
    (grpc,) = [p for p in _k8s_container()["ports"] if p["name"] == "grpc"]
    assert rule["ports"] == [{"protocol": "TCP", "port": grpc["containerPort"]}]
    assert 'dinerdash-client: "true"' in (DOCKER / "k8s" / "dinerdash.yaml").read_text()


def test_base_images_are_build_arguments_pinned_only_by_real_digests() -> None:
    """Each FROM names a build argument (or an earlier stage); a digest, where one is given, is
    a whole sha256. None is given: no digest can be checked from here (the Dockerfile says how
    to pin one), and none is made up."""
    lines = (DOCKER / "Dockerfile").read_text().splitlines()
    arguments = dict(
        line.removeprefix("ARG ").split("=", 1) for line in lines if line.startswith("ARG ")
    )
    froms = [line.split()[1] for line in lines if line.startswith("FROM ")]
    assert len(froms) == 3
    for image in froms:
        name = re.fullmatch(r"\$\{(\w+)\}", image)
        assert name, f"FROM {image}: name the base by a build argument"
        default = arguments[name.group(1)]
        if "@" in default:
            assert re.fullmatch(r"[\w./:-]+@sha256:[0-9a-f]{64}", default), default
    text = "\n".join(lines)
    assert "--build-arg DEBIAN_IMAGE=debian:bookworm-slim@sha256:" in text
    assert "offline-bases.sh" in text

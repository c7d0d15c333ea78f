"""The deployment files are safe when exposed: ``docker/Dockerfile``, ``docker/compose.yaml`` and
``docker/k8s/dinerdash.yaml`` start the server on every address (``--host 0.0.0.0``) only with a
token taken from a secret (an env file, a Kubernetes Secret), never on the command line and never
with ``--insecure``; the compose trainer gets the same token. Then the real binary, started with
the very arguments each file gives: without the token it refuses to start (before it binds
anything), and with it (moved to 127.0.0.1 and free ports) a client without the token is refused.

This stands in for ``make docker-smoke`` and ``make k8s-validate`` where no Docker engine or
cluster runs (CI)."""

from __future__ import annotations

import json
import secrets
import subprocess

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


def _k8s_container() -> dict:
    docs = list(yaml.safe_load_all((DOCKER / "k8s" / "dinerdash.yaml").read_text()))
    (deployment,) = [d for d in docs if d["kind"] == "Deployment"]
    (container,) = deployment["spec"]["template"]["spec"]["containers"]
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
def test_without_the_token_the_shipped_arguments_do_not_start(source: str) -> None:
    args = _shipped_args()[source]
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


def _on_loopback(args: list[str]) -> list[str]:
    """``args`` without ``--host``/``--port`` (LocalServer gives 127.0.0.1 and port 0), the
    metrics port a free one."""
    out: list[str] = []
    skip = False
    for i, arg in enumerate(args):
        if skip:
            skip = False
            continue
        if arg in ("--host", "--port"):
            skip = True
        elif arg == "--metrics-port":
            out += [arg, "0"]
            skip = True
        else:
            out.append(args[i])
    return out


@pytest.mark.parametrize("source", ["Dockerfile", "compose", "k8s"])
def test_with_the_token_a_client_without_it_is_refused(
    source: str, monkeypatch: pytest.MonkeyPatch
) -> None:
    token = secrets.token_hex(32)
    monkeypatch.setenv(TOKEN_VARIABLE, token)  # as the env file or the Secret sets it
    with LocalServer(server_binary(), args=_on_loopback(_shipped_args()[source])) as server:
        monkeypatch.delenv(TOKEN_VARIABLE)
        with pytest.raises(Unauthenticated):
            with Connection(server.address) as conn:
                conn.server_info()
        with pytest.raises(Unauthenticated):
            with Connection(server.address, token="not-the-token-0123456789") as conn:
                conn.server_info()
        with Connection(server.address, token=token) as conn:
            assert conn.server_info().live_sessions == 0

"""Packaging: one version everywhere, the order in which the client looks for the server binary,
where the ``dinerdash_server`` package finds the binary of its wheel, and the warning for a server
of another major/minor version.

The wheels themselves are installed and exercised in a clean venv by ``scripts/wheel_smoke.sh``
(``make wheel-smoke``); these tests run against the source tree, with fake executables.
"""

from __future__ import annotations

import os
import re
import shutil
import subprocess
import sys
import sysconfig
import warnings
from pathlib import Path

import dinerdash
import pytest
from dinerdash import ServerBinaryNotFound, ServerVersionWarning, _version
from dinerdash.server import find_server_binary

from .conftest import REPO, server_binary

SERVER_PACKAGE = REPO / "server" / "python" / "dinerdash_server"

pytestmark = pytest.mark.skipif(os.name == "nt", reason="fake executables are shell scripts")


def run(*cmd: str | os.PathLike[str], **kwargs) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [str(c) for c in cmd], capture_output=True, text=True, timeout=60, **kwargs
    )


def cargo_version() -> str:
    text = (REPO / "Cargo.toml").read_text()
    return re.search(r'\[workspace\.package\]\nversion = "([^"]+)"', text).group(1)


def fake_executable(path: Path, output: str = "") -> Path:
    """A shell script at ``path`` that prints ``output`` and its arguments."""
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(f'#!/bin/sh\necho "{output} $*"\n')
    path.chmod(0o755)
    return path


# -- one version ------------------------------------------------------------------------------


def test_every_copy_of_the_version_is_cargos() -> None:
    result = run(sys.executable, REPO / "scripts" / "version.py", "check")
    assert result.returncode == 0, result.stderr
    assert cargo_version() in result.stdout


def test_server_binary_and_client_report_the_same_version() -> None:
    result = run(server_binary(), "--version")
    assert result.returncode == 0, result.stderr
    assert result.stdout.strip() == f"dinerdash-server {cargo_version()}"
    # The editable install's metadata: the client's pyproject, which version.py keeps in step.
    assert dinerdash.__version__ == cargo_version()


def test_server_info_reports_the_binarys_version(address: str) -> None:
    with dinerdash.Connection(address) as conn:
        assert conn.server_info().server_version == cargo_version()


def test_version_set_rewrites_every_copy(tmp_path: Path) -> None:
    files = ["Cargo.toml", "Cargo.lock"]
    files += [f"{p}/pyproject.toml" for p in ("client-py", "agents", "bench")]
    for name in [*files, "scripts/version.py"]:
        (tmp_path / name).parent.mkdir(parents=True, exist_ok=True)
        shutil.copy(REPO / name, tmp_path / name)
    script = tmp_path / "scripts" / "version.py"
    result = run(sys.executable, script, "set", "3.4.5")
    assert result.returncode == 0, result.stderr
    assert run(sys.executable, script).stdout.strip() == "3.4.5"
    assert run(sys.executable, script, "check").returncode == 0
    client = (tmp_path / "client-py/pyproject.toml").read_text()
    assert '\nversion = "3.4.5"' in client and '"dinerdash-server==3.4.5"' in client
    for package in ("agents", "bench"):
        text = (tmp_path / package / "pyproject.toml").read_text()
        assert '\nversion = "3.4.5"' in text and '"dinerdash==3.4.5"' in text, package
    lock_text = (tmp_path / "Cargo.lock").read_text()
    assert 'name = "dinerdash-server"\nversion = "3.4.5"' in lock_text
    assert 'name = "dinerdash-proto"\nversion = "3.4.5"' in lock_text
    # Only the version lines changed.
    before = (REPO / "Cargo.toml").read_text().replace(cargo_version(), "3.4.5", 1)
    assert (tmp_path / "Cargo.toml").read_text() == before

    # A copy edited by hand is named.
    lock = tmp_path / "Cargo.lock"
    lock.write_text(lock.read_text().replace("3.4.5", "3.4.6"))
    result = run(sys.executable, script, "check")
    assert result.returncode == 1 and "Cargo.lock" in result.stderr and "3.4.6" in result.stderr
    assert run(sys.executable, script, "set", "not-a-version").returncode != 0


# -- where the client looks for the binary ----------------------------------------------------


@pytest.fixture
def fakes(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> dict[str, Path]:
    """A fake binary in each place the client looks, and a fake installed ``dinerdash_server``
    package whose ``find_binary`` returns one of them."""
    paths = {
        "argument": fake_executable(tmp_path / "argument" / "dinerdash-server"),
        "env": fake_executable(tmp_path / "env" / "dinerdash-server"),
        "package": fake_executable(tmp_path / "package-scripts" / "dinerdash-server"),
        "path": fake_executable(tmp_path / "path" / "dinerdash-server"),
    }
    package = tmp_path / "site" / "dinerdash_server"
    package.mkdir(parents=True)
    (package / "__init__.py").write_text(
        f"def find_binary():\n    return {str(paths['package'])!r}\n"
    )
    monkeypatch.syspath_prepend(str(package.parent))
    monkeypatch.delitem(sys.modules, "dinerdash_server", raising=False)
    monkeypatch.setenv("DINERDASH_SERVER", str(paths["env"]))
    monkeypatch.setenv("PATH", str(paths["path"].parent))
    return paths


def test_lookup_order(fakes: dict[str, Path], monkeypatch: pytest.MonkeyPatch) -> None:
    assert find_server_binary(fakes["argument"]) == fakes["argument"]
    assert find_server_binary() == fakes["env"]
    monkeypatch.delenv("DINERDASH_SERVER")
    assert find_server_binary() == fakes["package"]
    monkeypatch.setitem(sys.modules, "dinerdash_server", None)  # not installed: ImportError
    assert find_server_binary() == fakes["path"]
    monkeypatch.setenv("PATH", "")
    workspace = REPO / "target" / "release" / "dinerdash-server"
    assert workspace.is_file(), "the workspace build is the last resort; make builds it"
    assert find_server_binary() == workspace


def test_package_without_its_binary_is_passed_over(
    fakes: dict[str, Path], monkeypatch: pytest.MonkeyPatch, tmp_path: Path
) -> None:
    monkeypatch.delenv("DINERDASH_SERVER")
    broken = tmp_path / "broken" / "dinerdash_server"
    broken.mkdir(parents=True)
    (broken / "__init__.py").write_text(
        "def find_binary():\n    raise FileNotFoundError('no binary')\n"
    )
    monkeypatch.syspath_prepend(str(broken.parent))
    monkeypatch.delitem(sys.modules, "dinerdash_server", raising=False)
    assert find_server_binary() == fakes["path"]


def test_an_explicit_choice_that_is_wrong_is_an_error(
    fakes: dict[str, Path], monkeypatch: pytest.MonkeyPatch, tmp_path: Path
) -> None:
    missing = tmp_path / "missing" / "dinerdash-server"
    with pytest.raises(ServerBinaryNotFound) as e:
        find_server_binary(missing)
    assert "pip install 'dinerdash[server]'" in str(e.value) and str(missing) in str(e.value)
    monkeypatch.setenv("DINERDASH_SERVER", str(missing))
    with pytest.raises(ServerBinaryNotFound) as e:
        find_server_binary()
    message = str(e.value)
    assert "pip install 'dinerdash[server]'" in message and "DINERDASH_SERVER" in message


# -- the dinerdash_server package: where a wheel's binary lands --------------------------------


def installed_package(site: Path) -> None:
    """A copy of the real ``dinerdash_server`` package, as pip would put it into ``site``."""
    shutil.copytree(SERVER_PACKAGE, site / "dinerdash_server")


def find_binary_in(site: Path, scripts: Path, user_scripts: Path) -> str:
    """``dinerdash_server.find_binary()`` imported from ``site`` in a fresh interpreter, with the
    scheme's and the user scheme's scripts folders moved to ``scripts`` and ``user_scripts``."""
    code = (
        "import sysconfig\n"
        "def get_path(name, scheme=None, **kw):\n"
        f"    return {str(user_scripts)!r} if scheme else {str(scripts)!r}\n"
        "sysconfig.get_path = get_path\n"
        "import dinerdash_server\n"
        "try:\n"
        "    print(dinerdash_server.find_binary())\n"
        "except FileNotFoundError as e:\n"
        "    print('missing:', e)\n"
    )
    result = run(sys.executable, "-c", code, env={**os.environ, "PYTHONPATH": str(site)})
    assert result.returncode == 0, result.stderr
    return result.stdout.strip()


def test_find_binary_in_the_scripts_folders(tmp_path: Path) -> None:
    site = tmp_path / "venv" / "lib" / "python3" / "site-packages"
    installed_package(site)
    scripts, user = tmp_path / "venv" / "bin", tmp_path / "user" / "bin"
    assert find_binary_in(site, scripts, user).startswith("missing:")
    fake_executable(user / "dinerdash-server")
    assert find_binary_in(site, scripts, user) == str(user / "dinerdash-server")
    fake_executable(scripts / "dinerdash-server")  # the environment's own comes first
    assert find_binary_in(site, scripts, user) == str(scripts / "dinerdash-server")


def test_find_binary_with_pip_install_target(tmp_path: Path) -> None:
    target = tmp_path / "target"
    installed_package(target)
    binary = fake_executable(target / "bin" / "dinerdash-server")
    assert find_binary_in(target, tmp_path / "none", tmp_path / "none") == str(binary)


def test_find_binary_with_pip_install_prefix(tmp_path: Path) -> None:
    prefix = tmp_path / "prefix"
    site = prefix / "lib" / f"python{sys.version_info[0]}.{sys.version_info[1]}" / "site-packages"
    installed_package(site)
    binary = fake_executable(prefix / "bin" / "dinerdash-server")
    assert find_binary_in(site, tmp_path / "none", tmp_path / "none") == str(binary)


def test_find_binary_names_where_it_looked(tmp_path: Path) -> None:
    site = tmp_path / "site"
    installed_package(site)
    message = find_binary_in(site, tmp_path / "scripts", tmp_path / "user")
    assert message.startswith("missing:") and "pip install dinerdash-server" in message
    assert str(tmp_path / "scripts" / "dinerdash-server") in message
    assert str(site / "bin" / "dinerdash-server") in message


def test_python_m_dinerdash_server_runs_the_binary_with_its_arguments(tmp_path: Path) -> None:
    target = tmp_path / "target"
    installed_package(target)
    fake_executable(target / "bin" / "dinerdash-server", output="fake server:")
    # The interpreter's own scripts folder must not hold a real one for this to test --target.
    assert not (Path(sysconfig.get_path("scripts")) / "dinerdash-server").exists()
    result = run(
        sys.executable,
        "-m",
        "dinerdash_server",
        "eval",
        "--episodes",
        "3",
        cwd=tmp_path,
        env={**os.environ, "PYTHONPATH": str(target)},
    )
    assert result.returncode == 0, result.stderr
    assert result.stdout.strip() == "fake server: eval --episodes 3"


# -- a server of another version ----------------------------------------------------------------


@pytest.fixture
def fresh_warnings(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(_version, "_warned", set())


def test_other_major_or_minor_warns_once(fresh_warnings) -> None:
    with warnings.catch_warnings(record=True) as seen:
        warnings.simplefilter("always")
        _version.warn_if_other_version("0.1.9", "a:1", client_version="0.1.0")  # patch: fine
        _version.warn_if_other_version("0.2.0", "a:1", client_version="0.1.0")
        _version.warn_if_other_version("0.2.0", "b:2", client_version="0.1.0")  # once
        _version.warn_if_other_version("1.1.0", "a:1", client_version="0.1.0")
        _version.warn_if_other_version("unknown", "a:1", client_version="0.1.0")
        _version.warn_if_other_version("2.0.0", "a:1", client_version="0.0.0")  # source tree
    assert [w.category for w in seen] == [ServerVersionWarning, ServerVersionWarning]
    assert "dinerdash-server 0.2.0" in str(seen[0].message)
    assert "dinerdash[server]==0.1.0" in str(seen[0].message)
    assert "dinerdash-server 1.1.0" in str(seen[1].message)


def test_connecting_to_a_server_of_another_version_warns_once(
    address: str, fresh_warnings, monkeypatch: pytest.MonkeyPatch
) -> None:
    with dinerdash.Connection(address) as conn:
        server_version = conn.server_info().server_version
    major, minor = (int(part) for part in server_version.split(".")[:2])
    monkeypatch.setattr(_version, "__version__", f"{major}.{minor + 1}.0")
    with pytest.warns(ServerVersionWarning, match=re.escape(server_version)):
        dinerdash.Connection(address).close()
    with warnings.catch_warnings(record=True) as seen:
        warnings.simplefilter("always")
        dinerdash.Connection(address).close()
    assert not [w for w in seen if w.category is ServerVersionWarning]


def test_a_server_of_the_same_version_does_not_warn(address: str, fresh_warnings) -> None:
    with warnings.catch_warnings(record=True) as seen:
        warnings.simplefilter("always")
        dinerdash.Connection(address).close()
    assert not [w for w in seen if w.category is ServerVersionWarning]

"""The ``dinerdash-server`` binary, installed from a wheel: where it is.

The wheel carries the Rust binary itself (in the environment's scripts folder, beside ``pip``),
and this small package, which finds it::

    from dinerdash_server import find_binary
    subprocess.run([find_binary(), "eval", "--policy", "expert"])

``python -m dinerdash_server ARGS`` runs the binary with ``ARGS``. The Python client
(``pip install 'dinerdash[server]'``) starts this binary when it is given no server address.
"""

from __future__ import annotations

import os
import sysconfig
from importlib.metadata import PackageNotFoundError, version
from pathlib import Path

__all__ = ["BINARY_NAME", "find_binary"]

#: The binary's file name on this platform (``dinerdash-server.exe`` on Windows).
BINARY_NAME = "dinerdash-server" + (sysconfig.get_config_var("EXE") or "")

try:
    __version__ = version("dinerdash-server")
except PackageNotFoundError:  # imported from a source tree without installing
    __version__ = "0.0.0"


def _candidates() -> list[Path]:
    """The folders a wheel's scripts may have been installed into, most likely first."""
    # Not resolved: a symlinked site-packages (a venv's lib64) must keep its own parents.
    here = Path(os.path.abspath(__file__)).parent  # .../site-packages/dinerdash_server
    folders = [
        # The running interpreter's scheme: a virtual environment, or a plain install.
        Path(sysconfig.get_path("scripts")),
        # pip install --user.
        Path(sysconfig.get_path("scripts", scheme=sysconfig.get_preferred_scheme("user"))),
        # pip install --target DIR: DIR/dinerdash_server beside DIR/bin.
        here.parent / "bin",
        here.parent / "Scripts",
        # pip install --prefix DIR: DIR/lib/pythonX.Y/site-packages/dinerdash_server, DIR/bin.
        here.parents[3] / "bin" if len(here.parents) > 3 else None,
        # ... and on Windows DIR/Lib/site-packages/dinerdash_server, DIR/Scripts.
        here.parents[2] / "Scripts" if len(here.parents) > 2 else None,
    ]
    unique: list[Path] = []
    for folder in folders:
        if folder is not None and folder not in unique:
            unique.append(folder)
    return unique


def find_binary() -> str:
    """The path of the ``dinerdash-server`` binary this package was installed with.

    Looks in the current environment's scripts folder, then the user scheme's, then the
    ``--target`` and ``--prefix`` layouts relative to this package. Raises
    :class:`FileNotFoundError` naming every place it looked.
    """
    tried = []
    for folder in _candidates():
        path = folder / BINARY_NAME
        if path.is_file() and os.access(path, os.X_OK):
            return os.fspath(path)
        tried.append(os.fspath(path))
    raise FileNotFoundError(
        f"the {BINARY_NAME} binary of the dinerdash-server package is not installed "
        f"(looked at {', '.join(tried)}); reinstall it with `pip install dinerdash-server`"
    )

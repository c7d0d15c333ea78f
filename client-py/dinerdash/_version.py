"""The client's version, and the warning when it meets a server of another major/minor version
(docs/install.md#versions).
"""

from __future__ import annotations

import re
import threading
import warnings
from importlib.metadata import PackageNotFoundError, version

__all__ = ["ServerVersionWarning", "__version__", "warn_if_other_version"]

try:
    __version__ = version("dinerdash")
except PackageNotFoundError:  # running from a source tree without installing
    __version__ = "0.0.0"

_MAJOR_MINOR = re.compile(r"^\s*v?(\d+)\.(\d+)")
_warned: set[str] = set()
_warned_lock = threading.Lock()


class ServerVersionWarning(UserWarning):
    """The server's major/minor version (``ServerInfo.server_version``) is not the client's."""


def _major_minor(text: str) -> tuple[int, int] | None:
    match = _MAJOR_MINOR.match(text)
    return (int(match.group(1)), int(match.group(2))) if match else None


def warn_if_other_version(server_version: str, address: str, client_version: str | None = None):
    """Warns (once per server version in this process) when ``server_version`` differs from the
    client's in major or minor; unparseable versions and a source tree's ``0.0.0`` are not
    compared."""
    client_version = __version__ if client_version is None else client_version
    ours, theirs = _major_minor(client_version), _major_minor(server_version)
    if ours is None or theirs is None or ours == theirs or client_version == "0.0.0":
        return
    with _warned_lock:
        if server_version in _warned:
            return
        _warned.add(server_version)
    warnings.warn(
        f"the server at {address} is dinerdash-server {server_version} and this client is "
        f"dinerdash {client_version}: their major/minor versions differ, so replies may not be "
        f"what this client expects; install matching versions (pip install "
        f"'dinerdash[server]=={client_version}' for a local server)",
        ServerVersionWarning,
        stacklevel=2,
    )

"""The one version of the four distributions: `check` that they agree, or `set` a new one.

The source is the workspace's ``[workspace.package] version`` in ``Cargo.toml``: the server
crate inherits it, so ``dinerdash-server --version``, its ServerInfo and the ``dinerdash-server``
wheel (maturin reads Cargo) all carry it. The pure-Python packages keep a static copy, which
every tool can read without running code (sdists, editable installs, pip's resolver):

    client-py/pyproject.toml  version, and the [server] extra's ``dinerdash-server==VERSION``
    agents/pyproject.toml     version, and its ``dinerdash==VERSION`` dependency
    bench/pyproject.toml      the same
    Cargo.lock                the dinerdash-server and dinerdash-proto packages' versions (for
                              --locked builds)

``python scripts/version.py`` prints the version, ``check`` exits 1 naming every copy that
differs (``make wheels`` and tests/test_packaging.py run it), ``set 0.2.0`` rewrites them all.
"""

from __future__ import annotations

import re
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
SEMVER = re.compile(r"^\d+\.\d+\.\d+(?:[-.+][0-9A-Za-z.+-]+)?$")

# (file, pattern): group 1 is the text before the version, group 2 the version, group 3 after.
COPIES = [
    (
        "Cargo.toml",
        re.compile(r'(\[workspace\.package\]\nversion = ")([^"]+)(")'),
    ),
    (
        "Cargo.lock",
        re.compile(
            r'(\[\[package\]\]\nname = "dinerdash-server"\nversion = ")([^"]+)(")'
        ),
    ),
    (
        "Cargo.lock",
        re.compile(
            r'(\[\[package\]\]\nname = "dinerdash-proto"\nversion = ")([^"]+)(")'
        ),
    ),
    ("client-py/pyproject.toml", re.compile(r'(\nversion = ")([^"]+)(")')),
    ("client-py/pyproject.toml", re.compile(r'("dinerdash-server==)([^"]+)(")')),
    ("agents/pyproject.toml", re.compile(r'(\nversion = ")([^"]+)(")')),
    ("agents/pyproject.toml", re.compile(r'("dinerdash==)([^"]+)(")')),
    ("bench/pyproject.toml", re.compile(r'(\nversion = ")([^"]+)(")')),
    ("bench/pyproject.toml", re.compile(r'("dinerdash==)([^"]+)(")')),
]


def _find(file: str, pattern: re.Pattern[str]) -> re.Match[str]:
    text = (ROOT / file).read_text()
    matches = list(pattern.finditer(text))
    if len(matches) != 1:
        raise SystemExit(
            f"{file}: expected one match of {pattern.pattern!r}, found {len(matches)}"
        )
    return matches[0]


def workspace_version() -> str:
    """The version in Cargo.toml: the source of every other copy."""
    return _find(*COPIES[0]).group(2)


def mismatches() -> list[str]:
    """Every copy that differs from Cargo.toml's version, as ``file: found X, want Y``."""
    want = workspace_version()
    wrong = []
    for file, pattern in COPIES[1:]:
        found = _find(file, pattern).group(2)
        if found != want:
            wrong.append(
                f"{file}: {pattern.pattern} has {found}, Cargo.toml has {want}"
            )
    return wrong


def set_version(new: str) -> None:
    if not SEMVER.match(new):
        raise SystemExit(f"{new!r} is not a version like 1.2.3")
    for file, pattern in COPIES:
        path = ROOT / file
        match = _find(file, pattern)
        text = path.read_text()
        path.write_text(text[: match.start(2)] + new + text[match.end(2) :])


def main(argv: list[str]) -> int:
    if not argv:
        print(workspace_version())
        return 0
    if argv[0] == "check" and len(argv) == 1:
        wrong = mismatches()
        for line in wrong:
            print(line, file=sys.stderr)
        if not wrong:
            print(
                f"version {workspace_version()}: Cargo.toml, Cargo.lock and the pyprojects agree"
            )
        return 1 if wrong else 0
    if argv[0] == "set" and len(argv) == 2:
        set_version(argv[1])
        print(
            f"version {argv[1]} written to {', '.join(sorted({f for f, _ in COPIES}))}"
        )
        return 0
    print(__doc__, file=sys.stderr)
    return 2


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))

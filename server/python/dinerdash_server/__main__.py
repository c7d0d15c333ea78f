"""``python -m dinerdash_server ARGS``: runs the installed ``dinerdash-server`` binary with ARGS.

On POSIX the binary replaces this process (``exec``), so signals and the exit status are its
own; Windows has no ``exec`` that keeps the console, so there it runs as a child.
"""

from __future__ import annotations

import os
import sys

from . import find_binary


def main() -> None:
    binary = os.fsdecode(find_binary())
    if sys.platform == "win32":
        import subprocess

        sys.exit(subprocess.run([binary, *sys.argv[1:]]).returncode)
    os.execvp(binary, [binary, *sys.argv[1:]])


if __name__ == "__main__":
    main()

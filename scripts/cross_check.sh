#!/usr/bin/env bash
# `cargo check` of the server (library and binary) for the release wheels' other platforms, from
# Linux: Windows (x86_64-pc-windows-gnu; the release builds MSVC, whose std is the same code),
# macOS x86_64 and arm64, Linux aarch64. Unix-only code (signals, file limits) must sit behind cfg.
# Needs each target's standard library (`rustup target add TARGET`) and zig (the ziglang package
# of .build-venv, `make wheels` installs it) as the C compiler of ring's build script. Nothing is
# linked: a check, not a build. Usage: scripts/cross_check.sh [TARGET...]
set -euo pipefail
root="$(cd "$(dirname "$0")/.." && pwd)"
zig_python="$root/.build-venv/bin/python"
targets=("$@")
if [ "${#targets[@]}" -eq 0 ]; then
    targets=(x86_64-pc-windows-gnu x86_64-apple-darwin aarch64-apple-darwin aarch64-unknown-linux-gnu)
fi

tools="$(mktemp -d)"
trap 'rm -rf "$tools"' EXIT
printf '#!/bin/sh\nexec "%s" -m ziglang ar "$@"\n' "$zig_python" >"$tools/ar"
chmod +x "$tools/ar"

for target in "${targets[@]}"; do
    case "$target" in
        x86_64-pc-windows-gnu) zig_target=x86_64-windows-gnu ;;
        x86_64-apple-darwin) zig_target=x86_64-macos ;;
        aarch64-apple-darwin) zig_target=aarch64-macos ;;
        aarch64-unknown-linux-gnu) zig_target=aarch64-linux-gnu.2.17 ;;
        *) echo "cross-check: no zig target known for $target" >&2; exit 2 ;;
    esac
    # cc-rs adds --target=<rust triple>, which zig does not parse: the wrapper drops it.
    cat >"$tools/cc-$target" <<WRAPPER
#!/usr/bin/env bash
args=()
for a in "\$@"; do case "\$a" in --target=*) ;; *) args+=("\$a") ;; esac; done
exec "$zig_python" -m ziglang cc -target $zig_target "\${args[@]}"
WRAPPER
    chmod +x "$tools/cc-$target"
    var="${target//-/_}"
    echo "== cross-check: $target"
    env "CC_$var=$tools/cc-$target" "AR_$var=$tools/ar" \
        cargo check --release --locked -p dinerdash-server --lib --bins --target "$target"
done
echo "cross-check: ${#targets[@]} passed, 0 failed"

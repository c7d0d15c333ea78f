#!/usr/bin/env bash
# Builds the three base images that docker/Dockerfile names (debian:bookworm-slim,
# rust:1-slim-bookworm, python:3.11-slim-bookworm) on a host that cannot reach Docker Hub but can
# reach a Debian mirror. They stand in for the official images: Debian bookworm from debootstrap,
# this host's stable Rust toolchain, Debian's Python 3.11 with pip. The host's extra CA
# certificates (/usr/local/share/ca-certificates) go into the images, so that a TLS-inspecting
# proxy works from inside a build.
#
# Needs: root (run it as root, or with sudo where sudo exists), `debootstrap` (apt-get install
# debootstrap), a running Docker engine, and a rustup stable toolchain: the invoking user's
# (~/.rustup of $SUDO_USER under sudo, else of root), or wherever RUSTUP_HOME points.
#
#   docker/offline-bases.sh && make docker-smoke        # as root
#   sudo docker/offline-bases.sh && make docker-smoke   # as a user with sudo
set -euo pipefail

die() { echo "offline-bases.sh: $*" >&2; exit 1; }
[ "$(id -u)" -eq 0 ] || die "needs root (debootstrap and docker import): run it as root or with sudo"
command -v debootstrap >/dev/null || die "needs debootstrap: apt-get install debootstrap"
command -v docker >/dev/null || die "needs docker (a running Docker engine)"
# Under sudo, HOME is root's: the toolchain is the invoking user's.
user_home=$(getent passwd "${SUDO_USER:-$(id -un)}" | cut -d: -f6)
rustup_home=${RUSTUP_HOME:-${user_home:-$HOME}/.rustup}
toolchain=$rustup_home/toolchains/stable-x86_64-unknown-linux-gnu
[ -d "$toolchain/bin" ] || die "no rustup stable toolchain in $rustup_home (install rustup, \
run 'rustup toolchain install stable', or set RUSTUP_HOME)"
rustup_bin=$(command -v rustup || true)
[ -n "$rustup_bin" ] || rustup_bin=${user_home:-$HOME}/.cargo/bin/rustup
[ -x "$rustup_bin" ] || die "no rustup binary on PATH or in ${user_home:-$HOME}/.cargo/bin"

mirror=${DEBIAN_MIRROR:-http://deb.debian.org/debian}
work=$(mktemp -d)
trap 'rm -rf "$work"' EXIT

debootstrap --variant=minbase bookworm "$work/rootfs" "$mirror" >"$work/debootstrap.log"
rm -rf "$work/rootfs"/var/cache/apt/archives/*.deb "$work/rootfs"/var/lib/apt/lists/*
mkdir -p "$work/rootfs/usr/local/share/ca-certificates"
cp /usr/local/share/ca-certificates/*.crt "$work/rootfs/usr/local/share/ca-certificates/" 2>/dev/null || true
tar -C "$work/rootfs" -c . | docker import \
  -c 'ENV PATH=/usr/local/sbin:/usr/local/bin:/usr/sbin:/usr/bin:/sbin:/bin' -c 'CMD ["bash"]' \
  - debian:bookworm-slim

mkdir -p "$work/rust"
cp -a "$toolchain/bin" "$toolchain/lib" "$work/rust/"
cp "$rustup_bin" "$work/rust/rustup"
docker build -t rust:1-slim-bookworm -f - "$work/rust" <<'EOF'
FROM debian:bookworm-slim
ENV RUSTUP_HOME=/usr/local/rustup CARGO_HOME=/usr/local/cargo \
    PATH=/usr/local/cargo/bin:/usr/local/sbin:/usr/local/bin:/usr/sbin:/usr/bin:/sbin:/bin
RUN apt-get update && apt-get install -y --no-install-recommends ca-certificates gcc libc6-dev \
 && rm -rf /var/lib/apt/lists/*
COPY bin /usr/local/rustup/toolchains/stable-x86_64-unknown-linux-gnu/bin
COPY lib /usr/local/rustup/toolchains/stable-x86_64-unknown-linux-gnu/lib
COPY rustup /usr/local/cargo/bin/rustup
RUN printf 'version = "12"\ndefault_toolchain = "stable-x86_64-unknown-linux-gnu"\nprofile = "minimal"\n' \
      > /usr/local/rustup/settings.toml \
 && for t in cargo rustc rustdoc rustfmt cargo-fmt cargo-clippy; do ln -s rustup /usr/local/cargo/bin/$t; done \
 && cargo --version
EOF

docker build -t python:3.11-slim-bookworm - <<'EOF'
FROM debian:bookworm-slim
RUN apt-get update && apt-get install -y --no-install-recommends python3 python3-pip python-is-python3 ca-certificates \
 && rm -rf /var/lib/apt/lists/* /usr/lib/python3.11/EXTERNALLY-MANAGED \
 && ln -s /usr/bin/pip3 /usr/local/bin/pip \
 && printf '[global]\ncert = /etc/ssl/certs/ca-certificates.crt\n' > /etc/pip.conf \
 && python --version
EOF

#!/usr/bin/env bash
# Builds the three base images that docker/Dockerfile names (debian:bookworm-slim,
# rust:1-slim-bookworm, python:3.11-slim-bookworm) on a host that cannot reach Docker Hub but can
# reach a Debian mirror. They stand in for the official images: Debian bookworm from debootstrap,
# this host's stable Rust toolchain, Debian's Python 3.11 with pip. The host's extra CA
# certificates (/usr/local/share/ca-certificates) go into the images, so that a TLS-inspecting
# proxy works from inside a build. Needs root, debootstrap and a running Docker engine.
#
#   sudo docker/offline-bases.sh && make docker-smoke
set -euo pipefail

mirror=${DEBIAN_MIRROR:-http://deb.debian.org/debian}
toolchain=${RUSTUP_HOME:-$HOME/.rustup}/toolchains/stable-x86_64-unknown-linux-gnu
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
cp "$(command -v rustup)" "$work/rust/rustup"
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

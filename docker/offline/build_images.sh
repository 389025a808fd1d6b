#!/usr/bin/env bash
# Build the fleet's three images without Docker Hub: a Debian bookworm debootstrapped into a
# folder and imported, then Python, nginx and PostgreSQL on it (packages from the Debian
# mirror, Python packages from PyPI). Needs root, debootstrap and a running Docker engine.
#   docker/offline/build_images.sh [ROOTFS_FOLDER]
# Then start the fleet with these names (docker/smoke_test.sh does):
#   SWARMVO_BASE_IMAGE=swarmvo-offline/python:3.11 SWARMVO_NGINX_IMAGE=swarmvo-offline/nginx \
#   SWARMVO_POSTGRES_IMAGE=swarmvo-offline/postgres docker-compose -f docker/compose.yaml ...
set -euo pipefail
here="$(cd "$(dirname "$0")" && pwd)"
rootfs="${1:-/tmp/swarmvo-bookworm-rootfs}"
mirror="${DEBIAN_MIRROR:-http://deb.debian.org/debian}"
# Builds and their containers share the host's network (no NAT needed on the build host).
build=(docker build --network host)

if ! docker image inspect swarmvo-offline/debian:bookworm >/dev/null 2>&1; then
    if [ ! -x "$rootfs/usr/bin/apt-get" ]; then
        debootstrap --variant=minbase bookworm "$rootfs" "$mirror"
    fi
    tar -C "$rootfs" -c . | docker import - swarmvo-offline/debian:bookworm
fi
context="$(mktemp -d)"
trap 'rm -rf "$context"' EXIT
mkdir "$context/ca-certificates"
cp /usr/local/share/ca-certificates/*.crt "$context/ca-certificates/" 2>/dev/null || true
"${build[@]}" -t swarmvo-offline/python:3.11 -f "$here/python.Dockerfile" "$context"
"${build[@]}" -t swarmvo-offline/nginx -f "$here/nginx.Dockerfile" "$here"
"${build[@]}" -t swarmvo-offline/postgres -f "$here/postgres.Dockerfile" "$here"

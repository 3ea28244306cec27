#!/usr/bin/env bash
# Builds docker/Dockerfile with podman (no Docker engine needed), runs the image and renders one
# frame through it; prints the image size and how long each step took. Not run by scripts/test:
# the image build compiles kdrt-server from scratch inside the container (docs/scale-out.md, "The
# container image", has the times measured).
#
#   docker/build-image.sh              base image, build, run, one render
#   KDRT_IMAGE=localhost/kdrt:test ... another tag (default localhost/kdrt:latest)
#   KDRT_DEBIAN_MIRROR=http://...      the mirror debootstrap uses (default deb.debian.org)
#   KDRT_REBUILD_BASE=1 ...            make the debootstrap base image again
#
# The base image is Debian 12 made here with `debootstrap --variant=minbase bookworm` and
# `podman import` (localhost/kdrt-bookworm-minbase), used for both stages. Needs root (or
# sudo) for debootstrap and podman, and Debian's podman, runc and debootstrap packages
# (installed when missing). The container shares the host's network (--network host) and
# listens on a free loopback port.
set -euo pipefail
cd "$(dirname "${BASH_SOURCE[0]}")/.."

image=${KDRT_IMAGE:-localhost/kdrt:latest}
base=localhost/kdrt-bookworm-minbase:latest
mirror=${KDRT_DEBIAN_MIRROR:-http://deb.debian.org/debian}
sudo=()
if [ "$(id -u)" -ne 0 ]; then sudo=(sudo); fi
podman=("${sudo[@]}" podman --runtime runc)

missing=()
for pkg in podman runc debootstrap curl; do
    status=$(dpkg-query -W -f='${db:Status-Status}' "$pkg" 2>/dev/null || true)
    [ "$status" = installed ] || missing+=("$pkg")
done
if [ "${#missing[@]}" -gt 0 ]; then
    echo "build-image: installing ${missing[*]}"
    "${sudo[@]}" env DEBIAN_FRONTEND=noninteractive apt-get install -y --no-install-recommends \
        "${missing[@]}"
fi

step_start=0
step() {
    step_start=$(date +%s)
    echo "== $*"
}
took() { echo "   ($(($(date +%s) - step_start)) s)"; }
total_start=$(date +%s)

if [ "${KDRT_REBUILD_BASE:-0}" = 1 ] || ! "${podman[@]}" image exists "$base"; then
    step "base image $base (debootstrap --variant=minbase bookworm)"
    rootfs=$(mktemp -d)
    trap '"${sudo[@]}" rm -rf "$rootfs"' EXIT
    "${sudo[@]}" debootstrap --variant=minbase bookworm "$rootfs" "$mirror" >/dev/null
    "${sudo[@]}" tar -C "$rootfs" -c . | "${podman[@]}" import - "$base" >/dev/null
    "${sudo[@]}" rm -rf "$rootfs"
    trap - EXIT
    took
fi

step "podman build $image"
"${podman[@]}" build --network host --ulimit nofile=1024:20000 --ulimit nproc=4096:4096 \
    --ignorefile docker/Dockerfile.dockerignore \
    --build-arg BUILD_BASE="$base" --build-arg RUNTIME_BASE="$base" \
    -f docker/Dockerfile -t "$image" .
took
size=$("${podman[@]}" image inspect --format '{{.Size}}' "$image")
echo "   image size: $((size / 1000000)) MB ($size bytes)"

step "run $image and render one frame"
port=$(python3 -c 'import socket; s = socket.socket(); s.bind(("127.0.0.1", 0)); print(s.getsockname()[1])')
name="kdrt-image-test-$$"
"${podman[@]}" run -d --rm --name "$name" --network host --ulimit nofile=1024:20000 \
    --ulimit nproc=4096:4096 -e KDRT_LISTEN="127.0.0.1:$port" "$image" >/dev/null
cleanup() { "${podman[@]}" rm -f "$name" >/dev/null 2>&1 || true; }
trap cleanup EXIT
url="http://127.0.0.1:$port"
for _ in $(seq 1 100); do
    curl -fsS "$url/readyz" >/dev/null 2>&1 && break
    sleep 0.2
done
curl -fsS "$url/readyz" >/dev/null
id=$(curl -fsS --data-binary @tests/data/bunny00.off "$url/v1/meshes?format=off" |
    python3 -c 'import json, sys; print(json.load(sys.stdin)["id"])')
out=$(mktemp --suffix=.png)
curl -fsS -H 'Content-Type: application/json' \
    -d "{\"mesh\": \"$id\", \"width\": 256, \"height\": 192, \"shading\": \"eyelight\"}" \
    -o "$out" "$url/v1/render"
if [ "$(head -c 8 "$out" | od -An -tx1 | tr -d ' \n')" != 89504e470d0a1a0a ]; then
    echo "build-image: the render is not a PNG" >&2
    exit 1
fi
echo "   rendered mesh $id: $(stat -c %s "$out") bytes of PNG ($out)"
# SIGTERM drains and exits 0 (podman stop waits for it).
"${podman[@]}" stop -t 20 "$name" >/dev/null
trap - EXIT
took
echo "== build-image passed in $(($(date +%s) - total_start)) s: $image, $((size / 1000000)) MB"

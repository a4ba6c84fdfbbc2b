#!/usr/bin/env bash
# The system packages CloudLight-rs needs, in one list (the README's commands, .ci/run and the
# Dockerfile all start here), by role:
#   runtime: what `cloudlight` needs to run
#     mesa-vulkan-drivers libvulkan1   Vulkan lavapipe: the software GPU wgpu prefers on a GPU-less box
#     libegl-mesa0 libgl1-mesa-dri     EGL/GL llvmpipe: the second software adapter (WGPU_BACKEND=gl)
#     fonts-dejavu-core                text of the benchmark plots
#   build: what building it needs besides Rust
#     nasm g++                         openh264's C++ and x86 assembly (SIMD encode/decode), built from source
#   test: what its tests need
#     iproute2                         `ip netns` + veth for the network-namespace cluster test
#     ffmpeg                           ffprobe/ffmpeg: the independent decoder the video tests compare with
#     python3-venv                     a virtual environment for PyPI's kubernetes-validate (below)
#     libembree-dev                    Embree 3: the yardstick `bench rays --against-embree` and
#                                      the tests compare ray casting with (opened at run time)
# Usage: scripts/setup.sh [runtime|build|all] (default all: runtime + build + test);
#        scripts/setup.sh --list ROLE prints the packages of ROLE and does nothing else.
# Installed from Debian's archive with apt-get when run as root; otherwise prints the exact
# apt-get line and exits 1. Does nothing when everything is there already.
# CLOUDLIGHT_SKIP_SETUP=1 skips the check (a machine that provides the same libraries otherwise).
set -euo pipefail
runtime=(mesa-vulkan-drivers libvulkan1 libegl-mesa0 libgl1-mesa-dri fonts-dejavu-core)
build=(nasm g++)
test=(iproute2 ffmpeg python3-venv libembree-dev)
role_packages() {
  case "$1" in
    runtime) echo "${runtime[*]}" ;;
    build) echo "${runtime[*]} ${build[*]}" ;;
    all) echo "${runtime[*]} ${build[*]} ${test[*]}" ;;
    *) echo "setup: unknown role \`$1\` (runtime, build or all)" >&2; exit 2 ;;
  esac
}
if [ "${1:-}" = --list ]; then
  role_packages "${2:-all}"
  exit 0
fi
role="${1:-all}"
role_packages "$role" >/dev/null
read -r -a packages <<< "$(role_packages "$role")"

if [ "${CLOUDLIGHT_SKIP_SETUP:-0}" = 1 ]; then
  echo "setup: skipped (CLOUDLIGHT_SKIP_SETUP=1)" >&2
  exit 0
fi
if ! command -v dpkg-query >/dev/null 2>&1; then
  echo "setup: this is not a Debian-like system (no dpkg-query); install the equivalents of:" >&2
  echo "  ${packages[*]}" >&2
  echo "then run again with CLOUDLIGHT_SKIP_SETUP=1" >&2
  exit 1
fi
missing=()
for p in "${packages[@]}"; do
  status=$(dpkg-query -W -f='${Status}' "$p" 2>/dev/null || true)
  [ "$status" = "install ok installed" ] || missing+=("$p")
done
if [ ${#missing[@]} -gt 0 ]; then
  line="apt-get install -y --no-install-recommends ${missing[*]}"
  if [ "$(id -u)" != 0 ] || ! command -v apt-get >/dev/null 2>&1; then
    echo "setup: missing system packages: ${missing[*]}" >&2
    echo "install them as root, then run this command again:" >&2
    echo "  sudo apt-get update && sudo $line" >&2
    exit 1
  fi
  echo "setup: installing ${missing[*]}" >&2
  export DEBIAN_FRONTEND=noninteractive
  apt-get update -q >&2
  # A dpkg run stopped part-way (an install killed mid-upgrade) leaves packages unpacked but
  # not configured, and apt-get refuses to install anything until that is finished.
  if [ -n "$(dpkg --audit 2>/dev/null)" ]; then
    echo "setup: finishing an interrupted dpkg run first" >&2
    dpkg --configure -a >&2 || true
    apt-get install -f -y -q --no-install-recommends >&2
  fi
  # shellcheck disable=SC2086
  apt-get install -y -q --no-install-recommends "${missing[@]}" >&2
  echo "setup: done" >&2
fi
# The tests' Python tool, in its own virtual environment (PyPI's kubernetes-validate checks the
# generated Kubernetes manifests offline): $CLOUDLIGHT_VENV, default ~/.cache/cloudlight/venv.
if [ "$role" = all ]; then
  venv="${CLOUDLIGHT_VENV:-$HOME/.cache/cloudlight/venv}"
  if [ ! -x "$venv/bin/kubernetes-validate" ]; then
    echo "setup: installing kubernetes-validate into $venv" >&2
    python3 -m venv "$venv" >&2
    "$venv/bin/pip" install -q kubernetes-validate >&2
  fi
fi

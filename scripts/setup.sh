#!/usr/bin/env bash
# Installs every Debian package lcmx needs to build, test, run its demo and benchmarks.
# Idempotent: installs only what is missing, and runs `apt-get update` only when something is.
# Usage: scripts/setup.sh            (as root, Debian 12)
set -euo pipefail

packages=(
  build-essential cmake pkg-config git
  liblcm-dev liblcm-bin            # lcm-gen, liblcm (reference peer), lcm-logger
  libzmq3-dev cppzmq-dev           # Message Bridge
  libsodium-dev                    # group keys (lcmx::udpm, docs/keyed-groups.md)
  libboost-dev                     # Boost.Interprocess
  catch2 clang libclang-rt-14-dev  # tests (Catch2 v2; clang + libFuzzer runtime for test/fuzz)
  libcli11-dev libspdlog-dev libtomlplusplus-dev libncurses-dev
  zlib1g-dev                       # lcmx log export: MCAP CRC32
  python3 python3-jsonschema       # tests: the independent MCAP reader (test/integration/mcap_check.py)
  python3-dev pybind11-dev python3-pytest  # the Python module (python/) and its tests
  nlohmann-json3-dev               # lcmx::types from_json (lcmx pub)
  cyclonedds-dev cyclonedds-tools  # the DDS gateway (dds/: Cyclone DDS C API, idlc, ddsperf)
  iproute2 procps                  # network namespaces for multi-host tests, ps/pgrep
  tmux                             # tests of lcmx record/play on a terminal (status line, space bar)
  iperf3                           # bench/bridge: TCP reference on the emulated link
  graphviz                         # lcmx graph: SVG/PNG through dot
)

missing=()
for p in "${packages[@]}"; do
  if ! dpkg-query -W -f='${Status}' "$p" 2>/dev/null | grep -q "install ok installed"; then
    missing+=("$p")
  fi
done

if ((${#missing[@]} == 0)); then
  echo "setup: all ${#packages[@]} packages present"
  exit 0
fi

if [[ $(id -u) -ne 0 ]]; then
  echo "setup: missing packages: ${missing[*]}; run as root (or install them yourself)" >&2
  exit 1
fi
echo "setup: installing ${missing[*]}"
export DEBIAN_FRONTEND=noninteractive
if ! apt-get install -y --no-install-recommends "${missing[@]}"; then
  apt-get update
  apt-get install -y --no-install-recommends "${missing[@]}"
fi

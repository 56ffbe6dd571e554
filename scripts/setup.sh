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
  zlib1g-dev                       # discovery: compressed batches; lcmx log export: MCAP CRC32
  python3 python3-jsonschema       # tests: the independent MCAP reader (test/integration/mcap_check.py)
  python3-dev pybind11-dev python3-pytest  # the Python module (python/) and its tests
  nlohmann-json3-dev               # lcmx::types from_json (lcmx pub)
  cyclonedds-dev cyclonedds-tools  # the DDS gateway (dds/: Cyclone DDS C API, idlc, ddsperf)
  iproute2 procps                  # network namespaces for multi-host tests, ps/pgrep
  tmux                             # tests of lcmx record/play on a terminal (status line, space bar)
  iperf3                           # bench/bridge: TCP reference on the emulated link
  graphviz                         # lcmx graph: SVG/PNG through dot
  libssl-dev                       # lcmx foxglove: wss:// (Boost.Beast over OpenSSL)
  openssl                          # lcmx foxglove tests: a throwaway self-signed certificate (wss://)
)

missing=()
for p in "${packages[@]}"; do
  if ! dpkg-query -W -f='${Status}' "$p" 2>/dev/null | grep -q "install ok installed"; then
    missing+=("$p")
  fi
done

# Node.js and npm (Debian's nodejs + npm) for the tests of `lcmx foxglove`, which drive the real
# Foxglove client from npm. A machine that already has `node` and `npm` (e.g. another build of
# Node.js) keeps them: Debian's npm would conflict with it.
if ! command -v node >/dev/null 2>&1 || ! command -v npm >/dev/null 2>&1; then
  missing+=(nodejs npm)
fi

# The client packages, pinned exactly in test/foxglove/client/package-lock.json.
install_foxglove_client() {
  local dir
  dir="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)/test/foxglove/client"
  if [[ -f $dir/node_modules/.package-lock.json ]] && cmp -s "$dir/package-lock.json" "$dir/node_modules/.lcmx-installed-lock"; then
    return 0
  fi
  echo "setup: npm ci in $dir"
  (cd "$dir" && npm ci --no-audit --no-fund --loglevel=error) && cp "$dir/package-lock.json" "$dir/node_modules/.lcmx-installed-lock"
}

if ((${#missing[@]} == 0)); then
  echo "setup: all ${#packages[@]} packages present"
  install_foxglove_client
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
install_foxglove_client

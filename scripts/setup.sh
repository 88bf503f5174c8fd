#!/usr/bin/env bash
# Installs the Debian 12 packages DreamDojo.cpp needs and builds it into ./build.
#   scripts/setup.sh            install dependencies (apt) + configure + build
#   SKIP_APT=1 scripts/setup.sh build only
# On a GPU machine with PyTorch 2.x installed, CMake picks up its CUDA libtorch automatically.
set -euo pipefail
cd "$(dirname "$0")/.."

PACKAGES=(
  build-essential cmake ninja-build ccache pkg-config git python3
  libtorch-dev libopenblas0-pthread libgloo-dev      # libtorch 1.13 (CPU); fast BLAS; c10d headers
  python3-torch                                      # writes real torch.save files for the converter tests
  libavformat-dev libavcodec-dev libswscale-dev libavutil-dev ffmpeg
  nlohmann-json3-dev libcli11-dev libgtest-dev
  libmujoco-dev libosmesa6-dev                       # DojoSim physics + headless rendering
  libhdf5-dev                                        # EgoDex reader
  libsnappy-dev libzstd-dev                          # Parquet pages (LeRobot datasets)
  opencv-doc                                         # real camera clips used by the video tests
  libboost-dev libturbojpeg0-dev libsqlite3-dev      # dojo serve: HTTP/WebSocket, JPEG frames, votes
  libssl-dev                                         # dojo serve --tls-cert: HTTPS
  clang-format                                       # scripts/check_sources.py (CI)
  chromium nodejs npm                                # browser tests of the served pages
)

if [[ "${SKIP_APT:-0}" != 1 ]]; then
  SUDO=""
  if [[ $(id -u) -ne 0 ]]; then SUDO="sudo"; fi
  missing=()
  for p in "${PACKAGES[@]}"; do
    # A Node.js installed some other way (e.g. NodeSource, which bundles npm) serves as well.
    if [[ $p == nodejs || $p == npm ]] && command -v node >/dev/null && command -v npm >/dev/null; then continue; fi
    dpkg-query -W -f='${Status}' "$p" 2>/dev/null | grep -q "install ok installed" || missing+=("$p")
  done
  if ((${#missing[@]})); then
    echo "[setup] installing: ${missing[*]}"
    $SUDO apt-get update -qq
    DEBIAN_FRONTEND=noninteractive $SUDO apt-get install -y -qq --no-install-recommends "${missing[@]}" >/dev/null
  else
    echo "[setup] all Debian packages present"
  fi
fi

# playwright-core (npm) drives Debian's chromium in the browser tests; pinned by the lock file.
if [[ ! -d tests/browser/node_modules/playwright-core ]] && command -v npm >/dev/null; then
  npm ci --prefix tests/browser --no-audit --no-fund --loglevel=error
fi

JOBS="${JOBS:-$(nproc)}"
# DOJO_WERROR=ON (CI) makes every compiler warning an error. A cold build compiles the sources in
# batches (DOJO_UNITY_BUILD, docs/architecture.md): about half the time on 2 cores.
cmake -S . -B build -G Ninja -DCMAKE_BUILD_TYPE=Release -DDOJO_WARNINGS_AS_ERRORS="${DOJO_WERROR:-OFF}" \
  -DDOJO_UNITY_BUILD="${DOJO_UNITY:-ON}"
cmake --build build -j "$JOBS"
echo "[setup] built ./build/dojo"

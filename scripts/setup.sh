#!/usr/bin/env bash
# Set up Droneulator on a fresh Debian 12 / Ubuntu 24.04 machine:
#   Debian packages (Python venv, EGL + Mesa for headless rendering), then .venv with the package.
# Usage: bash scripts/setup.sh [--dev]     (--dev adds the test and lint tools and every workflow extra)
# Idempotent: packages already present are not reinstalled.
set -euo pipefail
cd "$(dirname "$0")/.."

extras="."
[[ "${1:-}" == "--dev" ]] && extras=".[dev,colmap,rl,ros,ray]"

debs=(python3 python3-venv python3-dev libegl1 libgl1 libegl-mesa0 libgl1-mesa-dri)
# --dev: the browser UI's tests drive Debian's Chromium with Playwright (tests/test_ui.py); the TLS tests
# make their certificates with the openssl CLI (tests/test_access.py, tests/test_zenoh_security.py)
[[ "${1:-}" == "--dev" ]] && debs+=(chromium openssl)
missing=()
for d in "${debs[@]}"; do
    dpkg-query -W -f='${Status}' "$d" 2>/dev/null | grep -q "install ok installed" || missing+=("$d")
done
if ((${#missing[@]})); then
    sudo=""
    [[ $(id -u) -ne 0 ]] && sudo="sudo"
    echo "setup: installing Debian packages: ${missing[*]}"
    $sudo apt-get update -qq
    DEBIAN_FRONTEND=noninteractive $sudo apt-get install -y -qq --no-install-recommends "${missing[@]}"
fi

py=${PYTHON:-python3}
"$py" -c 'import sys; assert sys.version_info >= (3, 11), "Python 3.11+ is required"'
[[ -x .venv/bin/python ]] || "$py" -m venv .venv
.venv/bin/python -m pip install -q --upgrade pip
if [[ "$extras" == *rl* ]]; then
    # the CPU build first: an unpinned resolution would fetch gigabytes of CUDA packages
    .venv/bin/python -m pip install -q "torch==2.13.0"
fi
.venv/bin/python -m pip install -q -e "$extras"
# the numba kernels compiled into their cache now rather than in the first run (droneulator compile --help)
.venv/bin/droneulator compile
echo "setup: ready ($(.venv/bin/python --version), $(.venv/bin/droneulator --help >/dev/null && echo droneulator OK))"

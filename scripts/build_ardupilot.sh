#!/usr/bin/env bash
# Build ArduCopter SITL (build/sitl/bin/arducopter) to fly Droneulator's vehicles (docs/ardupilot.md).
# Usage: bash scripts/build_ardupilot.sh        (about 8 minutes of waf on 2 cores; Debian: g++ make git
#                                                python3-venv)
# Env:
#   AP_WORK   work dir (default ~/.cache/droneulator/ardupilot): source in $AP_WORK/src, venv in $AP_WORK/venv
#   AP_COMMIT commit to build (default 90700977c5, upstream master of 2025-07-21, "ArduCopter V4.7.0-dev",
#             the commit Droneulator's link was checked against)
#   AP_REPO   where to clone from (default https://github.com/ArduPilot/ardupilot.git, with its submodules)
#   MIRROR    instead of AP_REPO: a directory of bare git snapshots <owner>+<name>/repo, for machines with no
#             network at build time (ArduPilot from $MIRROR/$AP_MIRROR, default
#             blitzy-public-samples+ardupilot-blitzy, a fork whose 90700977c5 is upstream's; submodules from
#             ArduPilot+waf, ArduPilot+mavlink, ArduPilot+pymavlink, dronecan+DSDL, dronecan+dronecan_dsdlc,
#             dronecan+libcanard, dronecan+pydronecan, ArduPilot+littlefs)
#   JOBS      parallel jobs (default nproc)
# Networking (lwip) and the unit tests (gtest) are configured off: SITL's sockets do not use lwip, and a
# snapshot build lacks their pinned commits.
set -euo pipefail
AP_WORK=${AP_WORK:-$HOME/.cache/droneulator/ardupilot}
AP_COMMIT=${AP_COMMIT:-90700977c5}
AP_REPO=${AP_REPO:-https://github.com/ArduPilot/ardupilot.git}
AP_MIRROR=${AP_MIRROR:-blitzy-public-samples+ardupilot-blitzy}
JOBS=${JOBS:-$(nproc)}
mkdir -p "$AP_WORK"; cd "$AP_WORK"
if [ ! -x venv/bin/python ]; then
  python3 -m venv venv
  # empy 3 (ArduPilot's generators need it), pydronecan needs pkg_resources (setuptools < 81)
  venv/bin/pip install -q empy==3.3.4 future pexpect "setuptools<81" lxml
fi
# snapshots leave out their largest blobs (CMSIS libraries, pictures, a mesh, a .tlog): SITL needs none
sparse_clone() {  # sparse_clone SOURCE DEST COMMIT
  git clone -q --no-checkout "$1" "$2"
  git -C "$2" config core.sparseCheckout true
  printf '%s\n' '/*' '!/libraries/AP_GyroFFT/CMSIS_5/lib/*.a' '!*.png' '!*.jpg' '!*.dae' '!*.tlog' \
    > "$(git -C "$2" rev-parse --absolute-git-dir)/info/sparse-checkout"
  git -C "$2" -c advice.detachedHead=false checkout -q --detach "$3"
}
if [ ! -d src/.git ]; then
  if [ -z "${MIRROR:-}" ]; then
    git clone -q "$AP_REPO" src
    git -C src -c advice.detachedHead=false checkout -q --detach "$AP_COMMIT"
    git -C src submodule update --init --recursive --depth 1 \
      modules/waf modules/mavlink modules/DroneCAN/DSDL modules/DroneCAN/dronecan_dsdlc \
      modules/DroneCAN/libcanard modules/DroneCAN/pydronecan modules/littlefs
  else
    sparse_clone "$MIRROR/$AP_MIRROR/repo" src "$AP_COMMIT"
    while read -r path snap; do
      pin=$(git -C src ls-tree HEAD "$path" | awk '{print $3}')
      echo "submodule $path @ $pin from $snap"
      rm -rf "src/$path"
      sparse_clone "$MIRROR/$snap/repo" "src/$path" "$pin"
      git -C src submodule init "$path" >/dev/null
    done <<LIST
modules/waf ArduPilot+waf
modules/mavlink ArduPilot+mavlink
modules/DroneCAN/DSDL dronecan+DSDL
modules/DroneCAN/dronecan_dsdlc dronecan+dronecan_dsdlc
modules/DroneCAN/libcanard dronecan+libcanard
modules/DroneCAN/pydronecan dronecan+pydronecan
modules/littlefs ArduPilot+littlefs
LIST
    pin=$(git -C src/modules/mavlink ls-tree HEAD pymavlink | awk '{print $3}')
    rm -rf src/modules/mavlink/pymavlink
    sparse_clone "$MIRROR/ArduPilot+pymavlink/repo" src/modules/mavlink/pymavlink "$pin"
  fi
fi
cd src
export PATH="$AP_WORK/venv/bin:$PATH"
start=$(date +%s)
./waf configure --board sitl --no-submodule-update --disable-networking --disable-tests
./waf copter -j"$JOBS"
echo "build took $(( $(date +%s) - start )) s: $AP_WORK/src/build/sitl/bin/arducopter"

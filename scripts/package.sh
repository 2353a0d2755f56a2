#!/usr/bin/env bash
# Build the one-folder PyInstaller bundle of the `droneulator` command and its tarball:
#   dist/droneulator/droneulator
#   dist/droneulator-<version>-linux-x86_64.tar.gz
# Usage: bash scripts/package.sh [--dist DIR] [--work DIR]
#   PYTHON=/path/to/python   the environment to freeze (default .venv/bin/python, made by scripts/setup.sh);
#                            pyinstaller is installed into it if missing.
# The bundle needs only the Debian EGL/Mesa libraries on the target (libegl1 libgl1 libegl-mesa0
# libgl1-mesa-dri); torch (train, evaluate) and pycolmap (reconstruct) stay out.
set -euo pipefail
root=$(cd "$(dirname "$0")/.." && pwd)
dist="$root/dist"
work="$root/build/pyinstaller"
while (($#)); do
    case "$1" in
        --dist) dist=$(realpath -m "$2"); shift 2 ;;
        --work) work=$(realpath -m "$2"); shift 2 ;;
        *) echo "package: unknown option $1 (see the header of $0)" >&2; exit 2 ;;
    esac
done
py=${PYTHON:-$root/.venv/bin/python}
if [[ ! -x "$py" ]]; then
    echo "package: no Python at $py: run bash scripts/setup.sh first, or set PYTHON" >&2
    exit 2
fi
if ! "$py" -c 'import PyInstaller' 2>/dev/null; then
    echo "package: installing pyinstaller into $("$py" -c 'import sys; print(sys.prefix)')"
    "$py" -m pip install -q "pyinstaller>=6.10"
fi
version=$(cd "$root" && "$py" -c 'import tomllib; print(tomllib.load(open("pyproject.toml", "rb"))["project"]["version"])')
arch=$(uname -m)

start=$SECONDS
rm -rf "$work"  # a fresh analysis every time; PyInstaller's own cache of binaries is kept
"$py" -m PyInstaller --noconfirm --log-level WARN \
    --distpath "$dist" --workpath "$work" "$root/packaging/droneulator.spec"
tarball="$dist/droneulator-$version-linux-$arch.tar.gz"
tar -C "$dist" -czf "$tarball" droneulator
echo "package: $dist/droneulator ($(du -sh "$dist/droneulator" | cut -f1)), $tarball ($(du -sh "$tarball" | cut -f1)), built in $((SECONDS - start)) s"

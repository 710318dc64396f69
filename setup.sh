#!/usr/bin/env bash
# Set up cellsight on a fresh Debian 12 machine (Python 3.11): system libraries, a virtual
# environment in .venv, the package and its extras. Idempotent: quick when already done.
#   ./setup.sh            runtime + benchmarks
#   ./setup.sh --test     runtime + test tools (and pyrealsense2, which the RealSense tests drive)
set -euo pipefail
cd "$(dirname "$0")"

extras="bench"
[ "${1:-}" = "--test" ] && extras="test,bench,realsense"

# Open3D 0.20 fails to import without libusb; the OpenNI2 driver needs libOpenNI2 and its
# Dummy device; a fresh Debian python3 needs python3-venv to make a virtual environment.
apt_pkgs=(libusb-1.0-0 libopenni2-dev libgomp1)
# The multi-host test builds its hosts from network namespaces with iproute2's `ip`.
[ "${1:-}" = "--test" ] && apt_pkgs+=(iproute2)
python3 -m venv --help >/dev/null 2>&1 && python3 -c 'import ensurepip' 2>/dev/null || apt_pkgs+=(python3-venv)
missing=()
for p in "${apt_pkgs[@]}"; do
  dpkg-query -W -f='${Status}' "$p" 2>/dev/null | grep -q "install ok installed" || missing+=("$p")
done
if [ ${#missing[@]} -gt 0 ]; then
  if [ "$(id -u)" -ne 0 ]; then
    echo "setup.sh: missing system packages. Run as root, then re-run ./setup.sh:" >&2
    echo "  apt-get update && apt-get install -y ${missing[*]}" >&2
    exit 1
  fi
  echo "setup.sh: installing ${missing[*]}"
  apt-get update -qq
  DEBIAN_FRONTEND=noninteractive apt-get install -y -qq "${missing[@]}" >/dev/null
fi

if [ ! -x .venv/bin/python ]; then
  python3 -m venv .venv
fi
stamp=".venv/.installed-$(sha1sum pyproject.toml | cut -c1-12)-${extras}"
if [ ! -f "$stamp" ]; then
  .venv/bin/python -m pip install -q --upgrade pip
  .venv/bin/python -m pip install -q -e ".[${extras}]" 2> >(grep -v "is ignored: it is neither a file" >&2)
  rm -f .venv/.installed-*
  touch "$stamp"
fi

#!/usr/bin/env bash
# Install plantsplat and everything it needs into ./.venv on a fresh Debian 12 machine.
#   bash scripts/install.sh          # the package and its runtime dependencies
#   bash scripts/install.sh --dev    # plus the test tools
# System packages (apt) are installed when missing and we are root (or sudo is available).
set -euo pipefail
cd "$(dirname "$0")/.."
EXTRAS="all"
if [[ "${1:-}" == "--dev" ]]; then EXTRAS="all,dev"; fi

# Debian packages: EGL/Mesa for the headless renderer (moderngl), libusb for Open3D's import.
APT_PKGS=(libegl1 libegl-mesa0 libgl1-mesa-dri libgles2 libusb-1.0-0 libgomp1)
# --dev: Chromium for the report's browser tests (driven by Playwright, no browser download).
if [[ "$EXTRAS" == *dev* ]]; then APT_PKGS+=(chromium); fi
missing=()
for p in "${APT_PKGS[@]}"; do
  dpkg-query -W -f='${Status}' "$p" 2>/dev/null | grep -q "install ok installed" || missing+=("$p")
done
if (( ${#missing[@]} )); then
  SUDO=""; [[ $(id -u) -ne 0 ]] && SUDO="sudo"
  echo "[install] apt packages: ${missing[*]}"
  $SUDO apt-get update -qq
  DEBIAN_FRONTEND=noninteractive $SUDO apt-get install -y -qq --no-install-recommends "${missing[@]}"
fi

PY=${PYTHON:-python3}
if [[ ! -x .venv/bin/python ]]; then
  echo "[install] creating .venv"
  "$PY" -m venv .venv
fi
.venv/bin/python -m pip install -q --upgrade pip
# torch is pinned by constraints.txt: the CPU wheel, never a CUDA download.
.venv/bin/python -m pip install -q -c constraints.txt -e ".[${EXTRAS}]"
echo "[install] done: $(.venv/bin/plantsplat --version)"

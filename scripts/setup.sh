#!/usr/bin/env bash
# Set up anchordp3 on Debian 12 (as root): system packages, a virtualenv in .venv, the package.
# Idempotent: a second run checks and returns in seconds.
set -euo pipefail
cd "$(dirname "$0")/.."

say() { printf '[setup] %s\n' "$*"; }
die() { printf '[setup] ERROR: %s\n' "$*" >&2; exit 1; }

# ---------------------------------------------------------------- system packages
apt_missing=()
version_of() { dpkg-query -W -f='${Version}' "$1" 2>/dev/null || true; }

have_gpu_vulkan() { ls /usr/share/vulkan/icd.d/nvidia_icd.json /etc/vulkan/icd.d/nvidia_icd.json >/dev/null 2>&1; }

mesa=$(version_of mesa-vulkan-drivers)
if ! have_gpu_vulkan && { [ -z "$mesa" ] || ! dpkg --compare-versions "$mesa" ge 24.3; }; then
  apt_missing+=(mesa-vulkan-drivers)
fi
for p in libusb-1.0-0 libvulkan1; do
  [ -n "$(version_of $p)" ] || apt_missing+=("$p")
done

if [ ${#apt_missing[@]} -gt 0 ]; then
  command -v apt-get >/dev/null || die "missing system packages (${apt_missing[*]}) and no apt-get: install Mesa lavapipe >= 24.3 (Vulkan on the CPU) and libusb-1.0 by hand"
  [ "$(id -u)" = 0 ] || die "missing system packages (${apt_missing[*]}); run this script as root, or: sudo apt-get install -t bookworm-backports ${apt_missing[*]}"
  say "installing system packages: ${apt_missing[*]}"
  if [[ " ${apt_missing[*]} " == *" mesa-vulkan-drivers "* ]] && ! grep -rqs "bookworm-backports" /etc/apt/sources.list /etc/apt/sources.list.d/; then
    echo "deb http://deb.debian.org/debian bookworm-backports main" > /etc/apt/sources.list.d/bookworm-backports.list
  fi
  export DEBIAN_FRONTEND=noninteractive
  apt-get update -qq || die "apt-get update failed: is the Debian package registry reachable?"
  for p in "${apt_missing[@]}"; do
    if [ "$p" = mesa-vulkan-drivers ]; then
      apt-get install -y -qq -t bookworm-backports mesa-vulkan-drivers >/dev/null \
        || die "could not install mesa-vulkan-drivers >= 24.3 from bookworm-backports; SAPIEN needs it to render without a GPU"
    else
      apt-get install -y -qq "$p" >/dev/null || die "could not install $p"
    fi
  done
fi

# ---------------------------------------------------------------- python environment
PY=${PYTHON:-python3}
if [ ! -x .venv/bin/python ]; then
  say "creating virtualenv .venv"
  if ! "$PY" -m venv .venv 2>/dev/null; then
    [ "$(id -u)" = 0 ] && apt-get install -y -qq python3-venv >/dev/null && "$PY" -m venv .venv \
      || die "could not create a virtualenv with $PY (install python3-venv)"
  fi
fi

stamp=.venv/.anchordp3-setup
want=$(cat pyproject.toml scripts/setup.sh | sha256sum | cut -d' ' -f1)
if [ "$(cat $stamp 2>/dev/null)" != "$want" ]; then
  say "installing python packages (torch==2.13.0 CPU wheel, sapien, ray, open3d, zarr, ...)"
  set +e
  .venv/bin/python -m pip install -q --disable-pip-version-check -e ".[test]" 2>&1 | grep -v "WARNING: Location"
  rc=${PIPESTATUS[0]}
  set -e
  [ "$rc" = 0 ] || die "pip install failed (exit $rc)"
  echo "$want" > $stamp
fi

# ---------------------------------------------------------------- check
.venv/bin/python - <<'PYCHECK' || die "the rendering check failed; see the message above"
import sapien
try:
    sapien.render.RenderSystem()
except RuntimeError as e:
    raise SystemExit(f"no Vulkan device for SAPIEN ({e}); on a CPU machine install Mesa lavapipe >= 24.3 from bookworm-backports")
PYCHECK
say "ready: .venv/bin/anchordp3"

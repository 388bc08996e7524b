#!/usr/bin/env bash
# One-command setup + run:  ./run.sh demo   |   ./run.sh test   |   ./run.sh shell
# Creates .venv (installing python3-venv with apt if this Debian/Ubuntu lacks it),
# installs libusb-1.0-0 with apt when missing (Open3D's wheel links it),
# installs torch==2.13.0 (CPU wheel where one is provided locally) and this package.
set -euo pipefail
cd "$(dirname "$0")"

pick_python() {
  for py in "${PYTHON:-}" python3.11 python3.12 python3.10 python3; do
    [ -n "$py" ] && command -v "$py" >/dev/null 2>&1 &&
      "$py" -c 'import sys; sys.exit(sys.version_info < (3, 10))' && { echo "$py"; return; }
  done
  echo "error: Python >= 3.10 not found (set PYTHON=/path/to/python3.11)" >&2; exit 1
}

apt_install() {  # system packages a fresh Debian/Ubuntu may lack
  local sudo=""; [ "$(id -u)" = 0 ] || sudo="sudo"
  command -v apt-get >/dev/null || { echo "error: please install: $*" >&2; exit 1; }
  $sudo apt-get update -qq && DEBIAN_FRONTEND=noninteractive $sudo apt-get install -y -qq "$@"
}

need_libusb() {  # Open3D (3D simulator and baselines) fails to import without it
  [ "$(uname -s)" = Linux ] || return 1
  compgen -G '/usr/lib/*/libusb-1.0.so.0' >/dev/null || compgen -G '/lib/*/libusb-1.0.so.0' >/dev/null ||
    { PATH="$PATH:/sbin:/usr/sbin" ldconfig -p 2>/dev/null | grep -q 'libusb-1.0.so.0'; } && return 1
  return 0
}

setup() {
  if need_libusb; then apt_install libusb-1.0-0; fi
  [ -f .venv/.installed ] && [ .venv/.installed -nt pyproject.toml ] && return
  local py; py=$(pick_python)
  rm -rf .venv
  if ! "$py" -m venv .venv 2>/dev/null; then
    rm -rf .venv
    apt_install "python3-venv" "$(basename "$py")-venv" || apt_install python3-venv
    "$py" -m venv .venv
  fi
  .venv/bin/python -m pip install -q --upgrade pip >/dev/null 2>&1 || true
  # exactly 2.13.0: a local CPU wheel here; the package itself accepts any torch >= 2.3
  .venv/bin/python -m pip install -q "torch==2.13.0"
  .venv/bin/python -m pip install -q -e ".[test]"
  touch .venv/.installed
}

setup
case "${1:-demo}" in
  demo) shift || true; exec .venv/bin/deepmapping demo "$@" ;;
  test) shift || true
    .venv/bin/ruff check -q src tests benchmarks  # style and lint (pyproject [tool.ruff])
    # import layers (pyproject [tool.importlinter]); prints its report only when a contract breaks
    layers=$(.venv/bin/lint-imports --no-cache 2>&1) || { echo "$layers"; exit 1; }
    exec .venv/bin/python -m pytest -q -n 2 "$@" ;;
  shell) exec bash --rcfile <(echo 'source .venv/bin/activate') ;;
  *) exec .venv/bin/deepmapping "$@" ;;
esac

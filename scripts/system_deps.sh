#!/usr/bin/env bash
# Installs the Debian shared libraries the Python wheels need (open3d: libusb, libgomp, libGL)
# and Debian's chromium (the viewer test drives it with playwright) when they are missing. Does nothing when they are present or when apt-get is unavailable.
set -euo pipefail
need=()
have_lib() { ldconfig -p 2>/dev/null | grep -q "$1"; }
have_lib 'libusb-1.0.so.0' || need+=(libusb-1.0-0)
have_lib 'libgomp.so.1' || need+=(libgomp1)
have_lib 'libGL.so.1' || need+=(libgl1)
have_lib 'libEGL.so.1' || need+=(libegl1)
command -v chromium >/dev/null 2>&1 || need+=(chromium)
if [ ${#need[@]} -eq 0 ]; then exit 0; fi
if ! command -v apt-get >/dev/null 2>&1; then
  echo "system_deps: missing ${need[*]} and no apt-get; install them with your package manager" >&2
  exit 0
fi
SUDO=""
if [ "$(id -u)" -ne 0 ]; then SUDO="sudo"; fi
echo "system_deps: installing ${need[*]}"
$SUDO apt-get update -qq
DEBIAN_FRONTEND=noninteractive $SUDO apt-get install -y -qq "${need[@]}" >/dev/null

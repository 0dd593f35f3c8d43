#!/usr/bin/env bash
# Installs what the HIL stage needs, idempotently and without prompts: qemu-system-arm 10.x
# (Debian bookworm-backports; bookworm's own is 7.2) and binutils-arm-none-eabi (the size report).
set -euo pipefail

as_root() { if [ "$(id -u)" = 0 ]; then "$@"; else sudo -n "$@"; fi; }

qemu_major() {
  qemu-system-arm --version 2>/dev/null | sed -n 's/^QEMU emulator version \([0-9]*\).*/\1/p'
}

if [ "$(qemu_major)" -ge 10 ] 2>/dev/null && command -v arm-none-eabi-size >/dev/null; then
  exit 0
fi

export DEBIAN_FRONTEND=noninteractive
# Add bookworm-backports once, unless some source already lists it.
if ! grep -rqs 'bookworm-backports' /etc/apt/sources.list /etc/apt/sources.list.d/; then
  as_root tee /etc/apt/sources.list.d/lightrig-bookworm-backports.sources >/dev/null <<'SRC'
Types: deb
URIs: http://deb.debian.org/debian
Suites: bookworm-backports
Components: main
Signed-By: /usr/share/keyrings/debian-archive-keyring.gpg
SRC
fi
as_root apt-get update -q
as_root apt-get install -y -q --no-install-recommends -t bookworm-backports qemu-system-arm
as_root apt-get install -y -q --no-install-recommends binutils-arm-none-eabi
qemu-system-arm --version | head -1
[ "$(qemu_major)" -ge 10 ] || { echo "qemu-system-arm 10.x expected" >&2; exit 1; }

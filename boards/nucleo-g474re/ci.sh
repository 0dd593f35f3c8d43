#!/usr/bin/env bash
# Builds the NUCLEO-G474RE bootloader and firmware for thumbv7em-none-eabihf (release, locked),
# the firmware in both galvo variants (DAC8563 on SPI, feature `xy2-100`) with an update key,
# and prints each size report against its partition (layout.rs): flash = .text + .rodata +
# .data (its load image), RAM = .data + .bss (+ stack above). Installs what it needs first,
# idempotently and without questions.
set -euo pipefail
cd "$(dirname "$0")"

rustup target add thumbv7em-none-eabihf >/dev/null

# A size tool: binutils for ARM from Debian, unless an ELF size tool is already there.
size_tool=""
for t in arm-none-eabi-size llvm-size; do
  if command -v "$t" >/dev/null 2>&1; then size_tool="$t"; break; fi
done
if [ -z "$size_tool" ]; then
  export DEBIAN_FRONTEND=noninteractive
  sudo=""; [ "$(id -u)" -ne 0 ] && sudo="sudo -n"
  $sudo apt-get update -qq
  $sudo apt-get install -y -qq binutils-arm-none-eabi >/dev/null
  size_tool=arm-none-eabi-size
fi

# The bootloader (its own crate beside this one): 24 KiB at the start of flash.
t0=$SECONDS
(cd ../nucleo-g474re-bootloader && cargo build --release --locked)
echo "build (bootloader): $((SECONDS - t0))s"
read -r text data bss _ < <("$size_tool" -B ../nucleo-g474re-bootloader/target/thumbv7em-none-eabihf/release/lightrig-nucleo-g474re-bootloader | tail -1)
printf 'size (bootloader): flash %d bytes (%d KiB of its 24 KiB partition)\n' "$((text + data))" $(((text + data + 1023) / 1024))
[ $((text + data)) -le $((24 * 1024)) ] || { echo "the bootloader outgrew its partition (layout.rs)" >&2; exit 1; }

# A key for the build check only (any public key builds the same code; labs build with theirs).
export LIGHTRIG_UPDATE_KEY=${LIGHTRIG_UPDATE_KEY:-5ca1ab1e5ca1ab1e5ca1ab1e5ca1ab1e5ca1ab1e5ca1ab1e5ca1ab1e5ca1ab1e}
elf=${CARGO_TARGET_DIR:-target}/thumbv7em-none-eabihf/release/lightrig-nucleo-g474re
# Both galvo outputs: the DAC8563 on SPI1 (default) and the XY2-100 link (feature `xy2-100`).
for variant in dac8563 xy2-100; do
  features=()
  [ "$variant" = xy2-100 ] && features=(--features xy2-100)
  t0=$SECONDS
  cargo build --release --locked "${features[@]}"
  echo "build ($variant): $((SECONDS - t0))s"
  "$size_tool" -A "$elf" | grep -E '^(section|\.vector_table|\.text|\.rodata|\.data|\.bss|\.uninit)' || true
  # Berkeley format: text (incl. rodata and the vector table), data, bss.
  read -r text data bss _ < <("$size_tool" -B "$elf" | tail -1)
  flash=$((text + data))
  ram=$((data + bss))
  printf 'size (%s): flash %d bytes (%d KiB of its 232 KiB partition), RAM %d bytes (%d KiB of 128 KiB, stack not included)\n' \
    "$variant" "$flash" $(((flash + 1023) / 1024)) "$ram" $(((ram + 1023) / 1024))
  [ "$flash" -le $((232 * 1024)) ] || { echo "the firmware outgrew the active partition (layout.rs)" >&2; exit 1; }
done

#!/usr/bin/env bash
# Starts the emulated board by hand: builds the firmware, runs it in QEMU with both UARTs on
# ptys (printed first), and decodes its defmt log with defmt-print if installed (else saves it
# to defmt.bin). `./run.sh bench` runs the benchmarks instead. Ctrl-C ends it.
set -euo pipefail
cd "$(dirname "$0")"
# Its own target directory and flags, whatever the caller has set for the root workspace.
unset CARGO_TARGET_DIR RUSTFLAGS CARGO_BUILD_TARGET
cargo build --release --locked
elf=target/thumbv7em-none-eabihf/release/lightrig-qemu
boot=$(od -An -N4 -tu4 /dev/urandom | tr -d ' ')
semi="enable=on,target=native,arg=lightrig,arg=boot=$boot"
serial=(-serial pty -serial pty)
if [ "${1:-}" = bench ]; then semi="$semi,arg=bench"; serial=(-serial stdio -serial null); fi
qemu-system-arm -M mps2-an386 -display none -monitor none -nodefaults \
  -icount shift=0,sleep=on "${serial[@]}" -semihosting-config "$semi" -kernel "$elf" |
  if [ "${1:-}" = bench ]; then cat; else
    IFS= read -r uart0; IFS= read -r uart1
    uart0=${uart0#char device redirected to }; uart1=${uart1#char device redirected to }
    echo "protocol UART0: ${uart0%% *}"
    echo "debug UART1:    ${uart1%% *}"
    if command -v defmt-print >/dev/null; then defmt-print -e "$elf"; else cat > defmt.bin; fi
  fi

#!/bin/sh
# Compile arduino/streamcal_bridge for an Arduino Uno with Debian's packaged toolchain
# (HARDWARE.md §7) and print flash/RAM use from avr-size.
#   tools/build_sketch.sh [BUILD_DIR]
# SC_BUILD_FLAGS (environment) adds compiler flags, e.g. SC_BUILD_FLAGS=-DSC_NO_SELFCAL builds the
# sketch without its own calibration (the baseline of tools/bench_firmware.py).
# Needs: apt-get install -y --no-install-recommends arduino-builder arduino-core-avr gcc-avr avr-libc binutils-avr
set -eu
here=$(cd "$(dirname "$0")/.." && pwd)
sketch="$here/arduino/streamcal_bridge/streamcal_bridge.ino"
build=${1:-$(mktemp -d "${TMPDIR:-/tmp}/streamcal-sketch.XXXXXX")}
mkdir -p "$build"
for tool in arduino-builder avr-size; do
    command -v "$tool" >/dev/null 2>&1 || { echo "build_sketch: $tool not found (install the packages above)" >&2; exit 127; }
done
# The extra -hardware dir provides the ctags recipe; -DDECIMAL_DIG works around ArduinoCore-avr
# issue #633 with Debian's gcc-avr 5.4 (both from HARDWARE.md §7). -mcall-prologues: one shared
# register save/restore instead of one per function (-0.7 KB flash, a few cycles per call).
arduino-builder -compile -hardware /usr/share/arduino-builder -hardware /usr/share/arduino/hardware \
    -tools /usr/bin -fqbn arduino:avr:uno -prefs runtime.ide.version=10819 \
    -prefs "compiler.cpp.extra_flags=-DDECIMAL_DIG=__DECIMAL_DIG__ -mcall-prologues ${SC_BUILD_FLAGS:-}" \
    -prefs "compiler.c.elf.extra_flags=-mcall-prologues" \
    -build-path "$build" "$sketch" >"$build/arduino-builder.log" 2>&1 || {
        cat "$build/arduino-builder.log" >&2; exit 1; }
avr-size -C --mcu=atmega328p "$build/streamcal_bridge.ino.elf"

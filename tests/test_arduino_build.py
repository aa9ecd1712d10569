"""The sketch builds for an Uno within budget, and its codec (sc_protocol.h, compiled with g++ on
the host) agrees byte for byte with the Python encoder on the shared test vectors."""
from __future__ import annotations

import json
import os
import re
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from firmware_bridge import frames as fr
from firmware_bridge.fake_board import sphere_sums_add

REPO = Path(__file__).resolve().parent.parent
VECTORS_DIR = REPO / "arduino" / "test_vectors"
FLASH_BUDGET = 14 * 1024   # bytes, target on an Uno (32 KB part, 0.5 KB bootloader), issue #15
RAM_BUDGET = 1228          # bytes of .data + .bss (1.2 KB of the 2 KB part; the rest is stack)

pytestmark = pytest.mark.toolchain


def _need(tool: str) -> str:
    path = shutil.which(tool)
    if path is None:
        message = (f"{tool} not found; install: apt-get install -y --no-install-recommends arduino-builder "
                   "arduino-core-avr gcc-avr avr-libc binutils-avr g++")
        if os.environ.get("CI"):
            pytest.fail(message)
        pytest.skip(message)
    return path


def test_vectors_file_matches_python_encoder():
    sys.path.insert(0, str(VECTORS_DIR))
    try:
        import make_vectors
    finally:
        sys.path.pop(0)
    stored = (VECTORS_DIR / "vectors.json").read_text()
    assert stored == make_vectors.render(), "vectors.json is stale: run arduino/test_vectors/make_vectors.py"
    data = json.loads(stored)
    for vec in data["frames"]:
        frame = fr.FrameDecoder().feed(bytes.fromhex(vec["hex"]))[0]
        assert (int(frame.type), frame.seq) == (vec["type"], vec["seq"])


@pytest.mark.slow
def test_sketch_builds_for_uno_within_budget(tmp_path):
    """The self-calibrating sketch (issue #15: <= 14 KB flash, <= 1.2 KB RAM); 14,160 B / 1,078 B
    when this was written (tools/bench_firmware.py compares it with -DSC_NO_SELFCAL)."""
    _need("arduino-builder")
    _need("avr-size")
    result = subprocess.run(["sh", str(REPO / "tools" / "build_sketch.sh"), str(tmp_path)],
                            capture_output=True, text=True, timeout=300)
    assert result.returncode == 0, result.stderr[-3000:]
    flash = int(re.search(r"Program:\s+(\d+) bytes", result.stdout).group(1))
    ram = int(re.search(r"Data:\s+(\d+) bytes", result.stdout).group(1))
    print(f"streamcal_bridge on an Uno: flash {flash} B, RAM {ram} B")
    assert flash <= FLASH_BUDGET, f"flash {flash} B > {FLASH_BUDGET} B"
    assert ram <= RAM_BUDGET, f"RAM {ram} B > {RAM_BUDGET} B"


@pytest.fixture(scope="module")
def sc_vectors(tmp_path_factory):
    gxx = _need("g++")
    exe = tmp_path_factory.mktemp("sc") / "sc_vectors"
    subprocess.run([gxx, "-std=c++11", "-Wall", "-Wextra", "-Werror", "-O1", "-ffp-contract=off",
                    "-o", str(exe), str(VECTORS_DIR / "sc_vectors.cpp")], check=True, timeout=120)

    def run(lines: list[str]) -> list[str]:
        out = subprocess.run([str(exe)], input="\n".join(lines) + "\n", capture_output=True, text=True,
                             timeout=60, check=True).stdout.splitlines()
        assert len(out) == len(lines)
        return out

    return run


@pytest.fixture(scope="module")
def vectors():
    return json.loads((VECTORS_DIR / "vectors.json").read_text())


def test_cpp_encodes_every_vector_byte_for_byte(sc_vectors, vectors):
    vecs = vectors["frames"]
    out = sc_vectors([" ".join(map(str, ["enc", v["type"], v["seq"], *v["args"]])) for v in vecs])
    for vec, got in zip(vecs, out):
        assert got == vec["hex"], vec["name"]


def test_cpp_decodes_python_bytes(sc_vectors, vectors):
    vecs = vectors["frames"]
    out = sc_vectors([f"dec {v['hex']}" for v in vecs])
    for vec, got in zip(vecs, out):
        assert got.split() == [str(x) for x in [vec["type"], vec["seq"], *vec["args"]]], vec["name"]


def test_cpp_rejects_damaged_frames(sc_vectors, vectors):
    out = sc_vectors([f"dec {v['hex']}" for v in vectors["bad"]])
    for vec, got in zip(vectors["bad"], out):
        assert got.startswith("ERR"), vec["name"]
        assert fr.FrameDecoder().feed(bytes.fromhex(vec["hex"])) == [], vec["name"]


def test_cpp_sphere_sums_equal_fake_board_sums(sc_vectors, vectors):
    mag = vectors["sums"]["mag"]
    got = sc_vectors(["acc " + " ".join(str(v) for row in mag for v in row)])[0]
    expected = sphere_sums_add(fr.SphereSums(), mag).values()
    assert [int(v) for v in got.split()] == expected == vectors["sums"]["args"]


def test_cpp_applies_calibration_like_fake_board(sc_vectors, vectors):
    cases = vectors["apply"]
    out = sc_vectors(["app " + " ".join(map(str, c["k"] + c["b"] + c["m"])) for c in cases])
    for case, got in zip(cases, out):
        assert [int(v) for v in got.split()] == case["x"]
    chk = vectors["cal_check"]
    crc, reason = sc_vectors(["chk " + " ".join(map(str, chk["k"] + chk["b"] + [chk["cal_id"]]))])[0].split()
    assert (int(crc), int(reason)) == (chk["crc"], 0)
    negative_k22 = chk["k"][:3] + [chk["k"][3] | 0x80000000] + chk["k"][4:]
    nan_b = chk["b"][:2] + [0x7FC00000]
    out = sc_vectors(["chk " + " ".join(map(str, k + b + [1])) for k, b in
                      ((negative_k22, chk["b"]), (chk["k"], nan_b))])
    assert [int(line.split()[1]) for line in out] == [fr.NakReason.BAD_CAL_VALUES] * 2


def test_sketch_builds_with_an_initial_calibration_header(tmp_path):
    """sc_initial_cal.h as `streamcal export --format c-header` writes it is compiled in."""
    _need("arduino-builder")
    sketch = tmp_path / "streamcal_bridge"
    shutil.copytree(REPO / "arduino" / "streamcal_bridge", sketch)
    (sketch / "sc_initial_cal.h").write_text(
        "#ifndef SC_INITIAL_CAL_H\n#define SC_INITIAL_CAL_H\n"
        "#define SC_INITIAL_CAL_K {48.5f, -1.25f, 0.75f, 51.0f, 2.5f, 49.75f}\n"
        "#define SC_INITIAL_CAL_B {12.0f, -7.5f, 30.25f}\n#endif\n")
    build = tmp_path / "build"
    build.mkdir()
    result = subprocess.run(
        ["arduino-builder", "-compile", "-hardware", "/usr/share/arduino-builder", "-hardware",
         "/usr/share/arduino/hardware", "-tools", "/usr/bin", "-fqbn", "arduino:avr:uno", "-prefs",
         "runtime.ide.version=10819", "-prefs", "compiler.cpp.extra_flags=-DDECIMAL_DIG=__DECIMAL_DIG__",
         "-build-path", str(build), str(sketch / "streamcal_bridge.ino")],
        capture_output=True, text=True, timeout=300)
    assert result.returncode == 0, result.stdout[-3000:] + result.stderr[-3000:]
    syms = subprocess.run(["avr-objdump", "-s", "-j", ".text", str(build / "streamcal_bridge.ino.elf")],
                          capture_output=True, text=True, check=True).stdout
    # the K row 48.5, -1.25 as little-endian float32 bytes is in flash (PROGMEM)
    blob = bytes.fromhex("".join(line[6:41].replace(" ", "") for line in syms.splitlines()
                                 if line.startswith(" ") and len(line) > 41))
    import struct
    assert struct.pack("<6f", 48.5, -1.25, 0.75, 51.0, 2.5, 49.75) in blob

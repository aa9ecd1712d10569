"""Byte-level corruptions of a rendered track file, shared by the fuzz suites.

``corrupt(text, ops, data)`` applies each named operation in turn to the UTF-8 bytes of
``text`` (drawing its random choices from hypothesis' ``data``) and returns the bytes to write.
"""
from __future__ import annotations

import gzip

from hypothesis import strategies as st


def _drop_header(blob: bytes) -> bytes:
    return b"\n".join(line for line in blob.split(b"\n")
                      if not line.startswith(b"t,") and b",t," not in line and not line.endswith(b",t"))


def corrupt(text: str, ops, data) -> bytes:
    blob = text.encode("utf-8")
    for op in ops:
        if op == "truncate":
            blob = blob[:data.draw(st.integers(0, len(blob)))]
        elif op == "insert_bytes":
            at = data.draw(st.integers(0, len(blob)))
            blob = blob[:at] + data.draw(st.binary(min_size=1, max_size=8)) + blob[at:]
        elif op == "flip" and blob:
            at = data.draw(st.integers(0, len(blob) - 1))
            blob = blob[:at] + bytes([blob[at] ^ data.draw(st.integers(1, 255))]) + blob[at + 1:]
        elif op == "utf16":
            blob = text.encode("utf-16")
        elif op == "latin1":
            blob = ("# unit: µT\n" + text).encode("latin-1")
        elif op == "gzip_cut":
            zipped = gzip.compress(blob)
            blob = zipped[:data.draw(st.integers(0, len(zipped)))]
        elif op == "gzip_garbage":
            blob = b"\x1f\x8b" + data.draw(st.binary(max_size=64))
        elif op == "gzip":
            blob = gzip.compress(blob)
        elif op == "empty":
            blob = b""
        elif op == "only_header":
            blob = b"t,mx,my,mz\n"
        elif op == "only_meta":
            blob = b"# streamcal-track: 1\n# sensor: x\n"
        elif op == "binary":
            blob = data.draw(st.binary(min_size=1, max_size=200))
        elif op == "drop_header":
            blob = _drop_header(blob)
        elif op == "long_line":
            blob = blob + b"1" * 200_000 + b",2\n"
        elif op == "crlf":
            blob = blob.replace(b"\n", b"\r\n")
        elif op == "blank_lines":
            blob = blob.replace(b"\n", b"\n\n# comment\n \n", data.draw(st.integers(0, 3)))
        elif op == "nul":
            blob = blob.replace(b",", b",\x00", 1)
    return blob

"""Test doubles for pyserial ports."""
from __future__ import annotations


class NullPort:
    """A pyserial-like port that records writes and has nothing to read."""

    in_waiting = 0

    def __init__(self):
        self.written = bytearray()

    def write(self, data):
        self.written += data
        return len(data)

    def read(self, n=1):
        return b""

    def close(self):
        pass

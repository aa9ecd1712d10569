"""Serial garbage: random and adversarial bytes into the frame decoder and the ``Raw:`` reader.

No crash, memory bounded (tracemalloc over 10 MB of garbage), resynchronisation at the next
valid frame, and losses counted exactly: valid frames with known sequence numbers interleaved
with garbage give ``received + lost == sent``.
"""
from __future__ import annotations

import tracemalloc

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from tests._ports import NullPort
from firmware_bridge import frames as fr
from firmware_bridge.rawlines import MAX_LINE, RawLineReader
from firmware_bridge.serial_link import SerialLink

GARBAGE_BYTES = 10 * 1024 * 1024
CHUNK = 4096
#: Peak extra Python memory while decoding 10 MB: the 4 kB chunk, its split parts, the
#: 254-byte frame buffer and the frames of one chunk; anything near the garbage size is a leak.
PEAK_BOUND = 256 * 1024


def sample_frame(seq: int) -> bytes:
    return fr.encode(fr.Sample(t_us=1000 * seq, mag=(seq % 1000, -3, 7), temp=1, status=1), seq)


def adversarial_garbage(rng: np.random.Generator, n: int) -> bytes:
    """``n`` bytes mixing uniform noise, delimiter look-alikes, COBS code bytes pointing past the
    end, long runs without a delimiter, truncated and CRC-damaged frames, and text."""
    parts, size = [], 0
    while size < n:
        kind = int(rng.integers(8))
        if kind == 0:
            p = rng.integers(0, 256, int(rng.integers(1, 600)), dtype=np.uint8).tobytes()
        elif kind == 1:
            p = bytes([0x01, 0x00, 0x02, 0xFF, 0x00, 0x00, 0xFE]) * int(rng.integers(1, 20))
        elif kind == 2:
            p = b"\xff" * int(rng.integers(255, 3000))        # oversized, no delimiter
        elif kind == 3:
            f = sample_frame(int(rng.integers(0, 65536)))
            p = f[:int(rng.integers(1, len(f) - 1))] + b"\x00"   # truncated
        elif kind == 4:
            f = bytearray(fr.encode_payload(fr.Sample(t_us=int(rng.integers(1 << 31))), 9))
            f[int(rng.integers(len(f)))] ^= 1 << int(rng.integers(8))
            p = fr.cobs.encode(bytes(f)) + b"\x00"             # CRC damage
        elif kind == 5:
            p = b"Raw:1,2,3,4,5,6,7,8,9\r\nUni:0,0\r\n" + b"x" * int(rng.integers(0, 300))
        elif kind == 6:
            p = fr.cobs.encode(b"\x01\x7f\x00\x00" + b"\x00" * int(rng.integers(0, 40))) + b"\x00"
        else:
            p = rng.integers(1, 256, int(rng.integers(1, 2000)), dtype=np.uint8).tobytes()
        parts.append(p)
        size += len(p)
    return b"".join(parts)[:n]


# ------------------------------------------------------------------------ memory over 10 MB

def _peak_while(feed, blob: bytes) -> int:
    tracemalloc.start()
    try:
        base = tracemalloc.get_traced_memory()[0]
        tracemalloc.reset_peak()
        view = memoryview(blob)
        for k in range(0, len(blob), CHUNK):
            feed(view[k:k + CHUNK])
        return tracemalloc.get_traced_memory()[1] - base
    finally:
        tracemalloc.stop()


@pytest.fixture(scope="module")
def ten_mb():
    return adversarial_garbage(np.random.default_rng(2024), GARBAGE_BYTES)


def test_frame_decoder_memory_bounded_over_10_mb_of_garbage(ten_mb):
    decoder = fr.FrameDecoder()
    peak = _peak_while(decoder.feed, ten_mb)
    print(f"\nFrameDecoder: 10 MB of garbage, peak traced memory {peak / 1024:.1f} kB; "
          f"stats {decoder.stats.as_dict()}")
    assert peak < PEAK_BOUND
    assert decoder.buffered <= decoder.max_encoded
    s = decoder.stats
    assert s.frames == 0      # (fixed seed) no damaged or random frame passes the CRC checks
    # every byte is accounted for: in a frame, in garbage, or waiting for its delimiter
    assert s.garbage_bytes + decoder.buffered + _frame_bytes(s.frames) <= len(ten_mb)
    assert s.rejected > 1000 and s.oversized > 0 and s.crc_errors > 0 and s.cobs_errors > 0
    # and it still decodes a clean frame afterwards
    assert [f.seq for f in decoder.feed(b"\x00" + sample_frame(77))] == [77]


def _frame_bytes(n_frames: int) -> int:
    return n_frames * len(sample_frame(0))


def test_raw_reader_memory_bounded_over_10_mb_of_garbage(ten_mb):
    reader = RawLineReader()
    rows = []
    peak = _peak_while(lambda chunk: rows.append(len(reader.feed(chunk))), ten_mb)
    print(f"\nRawLineReader: 10 MB of garbage, peak traced memory {peak / 1024:.1f} kB; "
          f"stats {reader.stats.as_dict()}")
    assert peak < PEAK_BOUND + 8 * len(rows)      # the list of row counts kept by the test
    assert len(reader._buf) <= MAX_LINE
    assert reader.stats.overlong > 0 and reader.stats.other_lines > 0
    got = reader.feed(b"\nRaw:1,2,3,4,5,6,7,8,-9\n")
    assert got.tolist() == [[1, 2, 3, 4, 5, 6, 7, 8, -9]]


# ------------------------------------------------------------------------ exact loss accounting

@settings(max_examples=60, deadline=None)
@given(seed=st.integers(0, 2**32 - 1), n=st.integers(2, 300), start=st.integers(0, 0xFFFF),
       chunk=st.integers(1, 700))
def test_losses_counted_exactly_with_garbage_between_frames(seed, n, start, chunk):
    """Frames with known sequence numbers, garbage between some of them (sometimes ending in a
    delimiter, sometimes glued to the next frame): every frame the decoder returns is one that
    was sent, in order, and received + lost == sent."""
    rng = np.random.default_rng(seed)
    stream, sent_seqs, resync = bytearray(), [], set()
    for i in range(n):
        seq = (start + i) & 0xFFFF
        if i and rng.random() < 0.4:
            junk = adversarial_garbage(rng, int(rng.integers(1, 400)))
            stream += junk
            if rng.random() < 0.5:
                stream += b"\x00"            # the garbage ends: the next frame must survive
                resync.add(seq)
        if i == n - 1:
            stream += b"\x00"                # the last frame is always clean (closes the count)
            resync.add(seq)
        stream += sample_frame(seq)
        sent_seqs.append(seq)
    decoder, counter = fr.FrameDecoder(), fr.SequenceCounter()
    got = []
    for k in range(0, len(stream), chunk):
        for f in decoder.feed(bytes(stream[k:k + chunk])):
            counter.observe(f.seq)
            got.append(f.seq)
    assert got[-1] == sent_seqs[-1]
    first = sent_seqs.index(got[0])
    assert counter.received + counter.lost == len(sent_seqs) - first
    assert set(got) <= set(sent_seqs) and got == sorted(got, key=sent_seqs.index)
    assert resync <= set(got), "a frame after a delimiter-terminated burst of garbage was lost"
    assert counter.received == decoder.stats.frames


def test_link_counts_losses_and_resyncs_in_frames_mode():
    """The same through :class:`SerialLink.feed` (the host's pure entry point)."""
    link = SerialLink(NullPort(), mode="frames")
    rng = np.random.default_rng(5)
    link.feed(fr.encode(fr.Hello(mag_scale=(0.15, 0.15, 0.15)), 0))   # scales; seq 0
    sent = 0
    for seq in range(1, 1001):
        if seq % 7 == 3:
            link.feed(adversarial_garbage(rng, 300) + b"\x00")
        if seq % 11 == 5:
            continue                               # dropped on the wire
        link.feed(sample_frame(seq))
        sent += 1
    s = link.stats
    assert s.frames == sent + 1
    assert s.frames + s.lost == 1001
    block = link.read_block(2000, timeout=0)
    assert len(block) == sent


# ------------------------------------------------------------------------ Raw: lines

@settings(max_examples=100, deadline=None)
@given(seed=st.integers(0, 2**32 - 1), n=st.integers(1, 200), chunk=st.integers(1, 300))
def test_raw_lines_recovered_after_junk_and_bad_lines_counted(seed, n, chunk):
    """Valid ``Raw:`` lines carrying their index, with junk lines, overlong lines, binary and
    ``Raw:`` lines with bad fields between them: every valid line that starts after a newline
    comes out exactly once, in order; the bad ones are counted."""
    rng = np.random.default_rng(seed)
    stream, expect, bad_raw = bytearray(b"\n"), [], 0
    for i in range(n):
        kind = int(rng.integers(6))
        if kind == 0:
            stream += b"Raw:1,2,3,4,5,6,7,8,x\n"; bad_raw += 1
        elif kind == 1:
            stream += b"Raw:1,2,3,4,5,6,7,8,40000\n"; bad_raw += 1
        elif kind == 2:
            stream += b"Raw:" + b"9" * 500 + b"\n"          # overlong
        elif kind == 3:
            stream += rng.integers(0, 256, 50, dtype=np.uint8).tobytes().replace(b"\n", b"") + b"\n"
        row = [i, -i, 3, 4, 5, 6, 7 * i % 30000, -8, 9]
        stream += b"Raw:" + ",".join(map(str, row)).encode() + b"\r\n"
        expect.append(row)
    reader = RawLineReader()
    got = [r for k in range(0, len(stream), chunk)
           for r in reader.feed(bytes(stream[k:k + chunk])).tolist()]
    assert got == expect
    assert reader.stats.lines == n
    assert reader.stats.bad_lines >= bad_raw


# ------------------------------------------------------------------------ hypothesis: anything

@settings(max_examples=200, deadline=None)
@given(st.lists(st.binary(max_size=400), max_size=15))
def test_any_bytes_into_the_link_never_crash(chunks):
    link = SerialLink(NullPort(), mode="auto")
    for chunk in chunks:
        link.feed(chunk)
        assert link._decoder.buffered <= link._decoder.max_encoded
        assert len(link._raw._buf) <= MAX_LINE
    block = link.read_block(10_000, timeout=0)
    assert block is None or np.all(np.isfinite(block.t))

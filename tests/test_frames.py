"""Frame codec: round trips, and damaged or hostile byte streams (counted, never fatal)."""
from __future__ import annotations

import struct

import numpy as np
import pytest
from crc import Calculator, Crc16
from hypothesis import given, settings
from hypothesis import strategies as st

from firmware_bridge import frames as fr

u8 = st.integers(0, 0xFF)
u16 = st.integers(0, 0xFFFF)
u32 = st.integers(0, 0xFFFFFFFF)
i16 = st.integers(-32768, 32767)
i64 = st.integers(-(1 << 63), (1 << 63) - 1)
f32 = st.floats(width=32, allow_nan=False)
_CODE = {"B": u8, "H": u16, "I": u32, "h": i16, "q": i64, "f": f32}


def message_strategy(cls):
    parts = {name: (_CODE[code] if count == 1 else st.tuples(*[_CODE[code]] * count))
             for name, code, count in cls.LAYOUT}
    return st.builds(cls, **parts)


any_message = st.one_of(*[message_strategy(cls) for cls in fr.MESSAGES.values()])


def sample_frames(n: int, start_seq: int = 0) -> list[bytes]:
    return [fr.encode(fr.Sample(t_us=1000 * i, mag=(i, -i, 2 * i), temp=i % 300, status=1), start_seq + i)
            for i in range(n)]


@given(st.binary(max_size=300))
def test_crc16_is_crc_ccitt_false_of_the_crc_package(data):
    assert fr.crc16(data) == Calculator(Crc16.IBM_3740.value).checksum(data)


def test_crc16_check_value():
    assert fr.crc16(b"123456789") == 0x29B1


@settings(max_examples=300)
@given(any_message, u16)
def test_every_message_round_trips(msg, seq):
    wire = fr.encode(msg, seq)
    assert wire.endswith(b"\x00") and b"\x00" not in wire[:-1]
    assert len(wire) <= fr.MAX_ENCODED + 1
    decoder = fr.FrameDecoder()
    frames = decoder.feed(wire)
    assert frames == [fr.Frame(seq=seq, msg=msg)]
    assert decoder.stats.rejected == 0 and decoder.stats.garbage_bytes == 0


@given(st.lists(any_message, min_size=1, max_size=20), st.data())
def test_chunking_does_not_matter(msgs, data):
    stream = b"".join(fr.encode(m, i) for i, m in enumerate(msgs))
    cuts = sorted(data.draw(st.lists(st.integers(0, len(stream)), max_size=30)))
    decoder, got = fr.FrameDecoder(), []
    for a, b in zip([0] + cuts, cuts + [len(stream)]):
        got += decoder.feed(stream[a:b])
    assert [f.msg for f in got] == msgs
    assert [f.seq for f in got] == list(range(len(msgs)))


@settings(max_examples=200)
@given(st.lists(st.binary(max_size=600), max_size=20))
def test_random_bytes_never_crash_and_memory_stays_bounded(chunks):
    decoder = fr.FrameDecoder()
    total = 0
    for chunk in chunks:
        decoder.feed(chunk)
        total += len(chunk)
        assert decoder.buffered <= decoder.max_encoded
    assert decoder.stats.garbage_bytes <= total


@settings(max_examples=100)
@given(st.lists(st.binary(min_size=1, max_size=80).map(lambda b: b.replace(b"\x00", b"\x01")), max_size=10),
       st.integers(5, 30))
def test_garbage_between_frames_is_counted_and_every_frame_recovered(garbage, n):
    good = sample_frames(n)
    stream = bytearray()
    for i, frame in enumerate(good):
        if i < len(garbage):
            stream += garbage[i] + b"\x00"
        stream += frame
    decoder = fr.FrameDecoder()
    got = decoder.feed(bytes(stream))
    assert [f.seq for f in got] == list(range(n))
    assert decoder.stats.garbage_bytes == sum(len(g) + 1 for g in garbage[:n])
    assert decoder.stats.rejected == min(len(garbage), n)


def test_bad_crc_is_counted_and_frame_dropped():
    frames = sample_frames(3)
    damaged = bytearray(fr.encode_payload(fr.Sample(t_us=5), 1))
    damaged[6] ^= 0x40
    stream = frames[0] + fr.cobs.encode(bytes(damaged)) + b"\x00" + frames[2]
    decoder = fr.FrameDecoder()
    assert [f.seq for f in decoder.feed(stream)] == [0, 2]
    assert decoder.stats.crc_errors == 1 and decoder.stats.rejected == 1


@pytest.mark.parametrize("cut", [1, 2, 5, 10, 20, 30])
def test_truncated_frame_is_counted_and_next_frame_survives(cut):
    a, b = sample_frames(2)
    decoder = fr.FrameDecoder()
    got = decoder.feed(a[:cut] + b"\x00" + b)
    assert [f.seq for f in got] == [1]
    assert decoder.stats.rejected == 1
    assert decoder.stats.garbage_bytes == cut + 1


def test_oversized_frame_is_dropped_with_bounded_buffer():
    decoder = fr.FrameDecoder()
    for _ in range(50):  # 5000 bytes without a delimiter, fed in pieces
        assert decoder.feed(b"\x07" * 100) == []
        assert decoder.buffered <= decoder.max_encoded
    got = decoder.feed(b"\x00" + sample_frames(1)[0])
    assert [f.seq for f in got] == [0]
    assert decoder.stats.oversized == 1
    assert decoder.stats.garbage_bytes == 5001


def test_repeated_delimiters_are_idle_not_errors():
    decoder = fr.FrameDecoder()
    got = decoder.feed(b"\x00\x00\x00" + b"\x00".join(sample_frames(3)) + b"\x00\x00")
    assert len(got) == 3 and decoder.stats.rejected == 0


def test_delimiter_lookalikes_inside_garbage():
    # bytes that look like COBS codes pointing at zeros, split by real zeros
    decoder = fr.FrameDecoder()
    junk = b"\x01\x00\x02\x01\x00\x03\x00\x00\xff\x00\x05\x01\x01\x01\x01\x00"
    got = decoder.feed(junk + sample_frames(1)[0])
    assert [f.seq for f in got] == [0]
    assert decoder.stats.rejected == 5


def test_foreign_version_and_unknown_type_and_bad_length_are_malformed():
    def wire(payload: bytes) -> bytes:
        return fr.cobs.encode(payload + fr.CRC.pack(fr.crc16(payload))) + b"\x00"

    decoder = fr.FrameDecoder()
    stream = (wire(fr.HEADER.pack(2, fr.MsgType.STOP, 0)) + wire(fr.HEADER.pack(1, 0x7F, 0))
              + wire(fr.HEADER.pack(1, fr.MsgType.STOP, 0) + b"\x01"))
    assert decoder.feed(stream) == []
    assert decoder.stats.malformed == 3


@given(st.integers(0, 0xFFFF), st.lists(st.booleans(), min_size=1, max_size=400), st.data())
def test_losses_counted_exactly_from_sequence_gaps(start, keep, data):
    keep[-1] = True  # the last frame sent arrives (otherwise its loss is invisible)
    counter = fr.SequenceCounter()
    for i, kept in enumerate(keep):
        if kept:
            counter.observe((start + i) & 0xFFFF)
    assert counter.received + counter.lost == len(keep) - keep.index(True)
    assert counter.lost == keep[keep.index(True):].count(False)


def test_end_to_end_losses_with_damage_on_the_line():
    rng = np.random.default_rng(3)
    n = 2000
    stream, sent = bytearray(), 0
    for i, frame in enumerate(sample_frames(n, start_seq=65000)):
        sent += 1
        r = rng.random() if i else 1.0                     # counting starts at the first frame
        if r < 0.03:
            continue                                        # lost on the line
        if r < 0.06:
            frame = frame[:-5] + b"\x00"                    # truncated
        elif r < 0.09:
            frame = bytearray(frame)
            frame[int(rng.integers(len(frame) - 1))] ^= 1 << int(rng.integers(8))
            frame = bytes(frame)                            # bit error (may split the frame)
        if rng.random() < 0.05:
            stream += rng.integers(1, 256, 20, dtype=np.uint8).tobytes()   # garbage glued to the frame
        stream += frame
    stream += sample_frames(1, start_seq=65000 + n)[0]      # a final good frame closes the count
    sent += 1
    decoder, counter = fr.FrameDecoder(), fr.SequenceCounter()
    for k in range(0, len(stream), 37):
        for f in decoder.feed(bytes(stream[k:k + 37])):
            counter.observe(f.seq)
    assert counter.received + counter.lost == sent
    assert counter.received == decoder.stats.frames
    assert decoder.stats.rejected > 0 and counter.lost > 0


def test_set_calibration_block_crc_and_matrices():
    K = np.array([[50.0, 1.5, -2.0], [0, 48.0, 0.25], [0, 0, 52.0]])
    cal = fr.SetCalibration.from_kb(K, [1.0, -2.0, 3.5], cal_id=9)
    assert cal.crc_ok()
    Kb, b = cal.matrices()
    np.testing.assert_array_equal(Kb, K)
    np.testing.assert_array_equal(b, [1.0, -2.0, 3.5])
    assert not fr.SetCalibration(cal_id=9, k=cal.k, b=(1.0, -2.0, 3.0), crc=cal.crc).crc_ok()
    assert cal.crc == fr.crc16(struct.pack("<H6f3f", 9, *cal.k, *cal.b))


def test_python_decodes_every_shared_vector_to_its_fields():
    """arduino/test_vectors/vectors.json (also checked byte for byte against the C++ codec in
    test_arduino_build.py): each frame decodes to the fields it was made from, SELF_CAL included
    (NaN stays NaN)."""
    import json
    import math
    from pathlib import Path

    data = json.loads((Path(__file__).resolve().parent.parent / "arduino" / "test_vectors" / "vectors.json").read_text())
    names = set()
    for vec in data["frames"]:
        frame = fr.FrameDecoder().feed(bytes.fromhex(vec["hex"]))[0]
        msg = frame.msg
        for key, want in vec["fields"].items():
            got = getattr(msg, key)
            for g, w in zip(np.atleast_1d(got), np.atleast_1d(want)):
                assert (math.isnan(g) and math.isnan(w)) or g == w, (vec["name"], key, got, want)
        names.add(vec["name"])
    assert {"self_cal_fitted", "self_cal_accepted"} <= names

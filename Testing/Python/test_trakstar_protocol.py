"""trakSTAR RS-232 protocol: word coding, record coding, framing and resynchronisation (no I/O)."""

from __future__ import annotations

import numpy as np
import pytest

from EMRegModule.devices.trakstar import protocol as tp
from EMRegModule.devices.trakstar.protocol import Pose, RecordParser

HALF_POSITION_STEP_MM = 0.5 * 4 * 36 / 32768 * 25.4
HALF_ANGLE_STEP_DEG = 0.5 * 4 * 180 / 32768


def test_word_decoding_equals_the_vendor_formula_for_every_14_bit_pattern():
    u = np.arange(1 << 14)
    data = np.empty(2 * len(u), dtype=np.uint8)
    data[0::2] = u & 0x7F
    data[1::2] = u >> 7
    raw = tp.decode_words(data.tobytes())
    expected = np.array([tp.word_value(int(lo), int(hi)) for lo, hi in zip(data[0::2], data[1::2], strict=True)])
    np.testing.assert_array_equal(raw * 4, expected)
    assert raw.min() == -8192 and raw.max() == 8191
    # the phasing bit does not change the value
    data[0::2] |= 0x80
    np.testing.assert_array_equal(tp.decode_words(data.tobytes()), raw)


def test_known_word_values():
    assert tp.word_value(0x00, 0x40) == -32768  # msb bit 6 -> sign
    assert tp.word_value(0x7F, 0x3F) == 32764
    assert tp.word_value(0x01, 0x00) == 4
    np.testing.assert_array_equal(tp.encode_words(np.array([1, -1])), bytes([0x01, 0x00, 0x7F, 0x7F]))


def test_quantise_rounds_to_14_bits_and_saturates():
    raw = tp.quantise([0.0, 36.0, -36.0, 100.0, 36.0 * 4 / 32768], 36.0)
    np.testing.assert_array_equal(raw, [0, 8191, -8192, 8191, 1])
    values = np.linspace(-35.9, 35.9, 1001)
    back = tp.raw_to_value(tp.quantise(values, 36.0), 36.0)
    assert np.max(np.abs(back - values)) <= 0.5 * 4 * 36 / 32768 + 1e-12


@pytest.mark.parametrize("name", list(tp.FORMATS))
def test_record_round_trip_every_format(name):
    fmt = tp.get_format(name)
    rng = np.random.default_rng(3)
    for _ in range(50):
        pose = Pose(rng.uniform(-800, 800, 3), np.array([rng.uniform(-180, 180), rng.uniform(-89, 89),
                                                          rng.uniform(-180, 180)]))
        data = tp.encode_record(fmt, pose, 36, metal=17, address=3)
        assert len(data) == tp.record_length(fmt, metal=True, group=True) == 2 * fmt.words + 2
        assert data[0] & 0x80 and not any(b & 0x80 for b in data[1:])
        record = tp.decode_record(fmt, data, 36, metal=True, group=True)
        assert record.metal == 17 and record.address == 3 and tp.record_values_plausible(record)
        if fmt.has("position"):
            assert np.max(np.abs(record.position_mm - pose.position_mm)) <= HALF_POSITION_STEP_MM + 1e-9
        if fmt.has("angles"):
            diff = (record.angles_deg - pose.angles_deg + 180) % 360 - 180
            assert np.max(np.abs(diff)) <= HALF_ANGLE_STEP_DEG + 1e-9
        if fmt.has("matrix"):
            assert np.max(np.abs(record.matrix - pose.rotation)) <= 4 / 32768 + 1e-9
        if fmt.has("quaternion"):
            assert np.max(np.abs(record.quaternion - pose.quaternion)) <= 4 / 32768 + 1e-9
        rotation = record.rotation()
        if rotation is not None:
            angle = np.degrees(np.arccos(np.clip((np.trace(rotation.T @ pose.rotation) - 1) / 2, -1, 1)))
            assert angle < 0.05


def test_word_counts_and_commands_match_the_protocol():
    counts = {f.name: f.words for f in tp.FORMATS.values()}
    assert counts == {"POSITION": 3, "ANGLES": 3, "MATRIX": 9, "POSITION/ANGLES": 6, "POSITION/MATRIX": 12,
                      "QUATERNION": 4, "POSITION/QUATERNION": 7}
    assert [chr(f.command) for f in tp.FORMATS.values()] == ["V", "W", "X", "Y", "Z", "\\", "]"]
    assert tp.address_byte(1) == 0xF1 and tp.address_byte(4) == 0xF4
    assert tp.POINT == ord("B") and tp.STREAM == ord("@")
    assert tp.CHANGE_VALUE == ord("P") and tp.EXAMINE_VALUE == ord("O")
    assert tp.POWER_ON_FORMAT.name == "POSITION/ANGLES" and tp.POWER_ON_SCALE_INCHES == 36


def test_line_limited_rate():
    fmt = tp.get_format("POSITION/ANGLES")
    # 4 sensors x (12 data + METAL + address) = 56 bytes per cycle; 11520 bytes/s at 115200 baud
    assert tp.max_stream_rate_hz(fmt, 4, 115200, metal=True) == pytest.approx(11520 / 56)


def _records(n: int, fmt=tp.FORMATS["POSITION/ANGLES"], group=True) -> list[bytes]:
    rng = np.random.default_rng(0)
    out = []
    for i in range(n):
        pose = Pose(rng.uniform(-300, 300, 3), np.array([10.0, 20.0, 30.0]))
        out.append(tp.encode_record(fmt, pose, 36, metal=0, address=(i % 4) + 1 if group else None))
    return out


def test_parser_accepts_clean_stream_in_any_chunking():
    records = _records(40)
    stream = b"".join(records)
    for chunk in (1, 3, 14, 100, len(stream)):
        parser = RecordParser(14, frozenset({1, 2, 3, 4}))
        got = []
        for i in range(0, len(stream), chunk):
            got += parser.feed(stream[i:i + chunk], 0)
        assert got == records and parser.stats.rejected == 0


def test_parser_resynchronises_after_drops_flips_and_noise():
    records = _records(12)
    damaged = list(records)
    damaged[2] = damaged[2][:5] + damaged[2][6:]  # dropped byte
    damaged[5] = damaged[5][:7] + bytes([damaged[5][7] | 0x80]) + damaged[5][8:]  # phasing bit set mid-record
    damaged[8] = bytes([damaged[8][0] & 0x7F]) + damaged[8][1:]  # phasing bit lost on the first byte
    stream = b"\x05\x06" + b"".join(damaged)  # stray bytes before the first record
    parser = RecordParser(14, frozenset({1, 2, 3, 4}))
    got = parser.feed(stream, 0)
    # record 7 is good but is followed by a byte that is not a record start: dropped too (safe side)
    assert got == [r for i, r in enumerate(records) if i not in (2, 5, 7, 8)]
    assert parser.stats.phase_errors >= 2 and parser.stats.stray_bytes > 0 and parser.stats.follow_errors == 1


def test_parser_rejects_wrong_address_extra_byte_and_long_silence():
    records = _records(3)
    bad_address = records[0][:-1] + bytes([9])
    parser = RecordParser(14, frozenset({1, 2, 3, 4}))
    assert parser.feed(bad_address + records[1], 0) == [records[1]]
    assert parser.stats.address_errors == 1
    # an extra data byte: the record looks complete but the next byte is not a record start
    extra = records[0][:4] + b"\x11" + records[0][4:]
    parser = RecordParser(14, frozenset({1, 2, 3, 4}))
    assert parser.feed(extra + records[1], 0) == [records[1]]
    assert parser.stats.follow_errors == 1
    # a record interrupted by a long silence is dropped (its bytes were lost and others spliced in)
    parser = RecordParser(14, frozenset({1, 2, 3, 4}), max_gap_ns=10_000_000)
    assert parser.feed(records[0][:6], 0) == []
    assert parser.feed(records[0][6:] + records[1], 50_000_000) == [records[1]]
    assert parser.stats.gap_errors == 1
    assert parser.ends == [parser.offset]  # where the accepted record ended in the byte stream
    # ... but bytes that were already waiting when a late reader read them say nothing about the line
    parser = RecordParser(14, frozenset({1, 2, 3, 4}), max_gap_ns=10_000_000)
    assert parser.feed(records[0][:6], 0) == []
    assert parser.feed(records[0][6:] + records[1], 50_000_000, timed=False) == [records[0], records[1]]
    assert parser.stats.gap_errors == 0 and parser.ends == [14, 28]


def test_value_checks_reject_impossible_orientations():
    fmt = tp.FORMATS["POSITION/ANGLES"]
    data = bytearray(tp.encode_record(fmt, Pose(np.array([100.0, 0, 0]), np.array([0.0, 45.0, 0])), 36))
    data[9] ^= 0x20  # elevation MSB bit -> beyond +-90 degrees
    assert not tp.record_values_plausible(tp.decode_record(fmt, bytes(data), 36))
    fmt = tp.FORMATS["POSITION/QUATERNION"]
    data = bytearray(tp.encode_record(fmt, Pose(np.array([100.0, 0, 0]), np.array([30.0, 20.0, 10.0])), 36))
    data[7] ^= 0x10
    assert not tp.record_values_plausible(tp.decode_record(fmt, bytes(data), 36))
    zero = tp.decode_record(fmt, tp.zero_record(fmt), 36)
    assert zero.all_zero and tp.record_values_plausible(zero)

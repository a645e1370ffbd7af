"""MIMU4444 stream importer (accel_bayes.data.mimu, mimu_packets, mimu_decode, mimu_report) and ``accel-bayes import-mimu``.

Two halves:

* hand-made byte streams (built with ``struct``, independently of the importer's numpy dtype):
  checksum failures, trailing partial packets, 2^32 timestamp wraps, 2^16 packet-number wraps,
  gaps, gzip vs plain, missing ack, non-MIMU input;
* the six shared recordings (``../shared/data/mimu4444-bcd``; skipped only if absent): the
  issue's MUST-SHOW figures — no checksum failure, 20 distinct rest orientations, |acc| at rest
  within 0.15 m/s² of 9.81, top and bottom IMUs agreeing within 15° in every rest.

Issue #13 (damaged streams): swapped, repeated and conflicting packets, lost and inserted bytes,
both wraps under reordering, stamps and numbers off the grid, and the real recordings flagging
nothing; the plausibility checks and the fuzz test are in ``test_mimu_fuzz.py``.
"""
import gzip
import hashlib
import math
import struct
import time as _time

import numpy as np
import pytest
import torch

from accel_bayes.physics.arrays import G0, MIMU_BOTTOM_QUAT, mimu4444_8
from accel_bayes.errors import RecordingError
from accel_bayes.physics.geometry import quat_to_matrix
from accel_bayes.data.mimu import import_mimu
from accel_bayes.data.mimu_decode import decode_mimu_bytes, read_mimu_stream
from accel_bayes.data.mimu_packets import ACC_SCALE, GYRO_SCALE, MIMU_ACK, encode_mimu_packets
from accel_bayes.data.segments import angle_deg

EXPERIMENTS = [f"exp_{i}" for i in range(1, 7)]
PERIOD = 1_024_000  # ticks of 64 MHz per 16 ms


# ---------------------------------------------------------------------------------------- hand-made streams
def _packet(number: int, stamp: int, raw48) -> bytes:
    """One 106-byte packet, written field by field with struct (big-endian)."""
    body = struct.pack(">BHBI48h", 0xAA, number % 65536, 100, stamp % (1 << 32), *[int(v) for v in raw48])
    return body + struct.pack(">H", sum(body) % 65536)


def _stream(n=60, first_number=100, first_stamp=1_000_000, seed=0, ack=True, jitter=True, numbers=None, stamps=None,
            span=30):
    # span 30: independent ±30-LSB values per IMU, a board at rest, which the rigid-board check
    # never questions (issue #29: values no rigid body makes are dropped, so a wide span would
    # lose packets to that check in tests of the framing).
    rng = np.random.default_rng(seed)
    raw = rng.integers(-span, span, size=(n, 48))
    if numbers is None:
        numbers = first_number + np.arange(n)
    if stamps is None:
        steps = PERIOD + (rng.integers(-8, 9, size=n - 1) if jitter else np.zeros(n - 1, dtype=np.int64))
        stamps = first_stamp + np.concatenate(([0], np.cumsum(steps)))
    data = b"".join(_packet(int(k), int(s), r) for k, s, r in zip(numbers, stamps, raw))
    return (MIMU_ACK if ack else b"") + data, np.asarray(numbers), np.asarray(stamps, dtype=np.int64), raw


def test_struct_stream_decodes_exactly():
    data, numbers, stamps, raw = _stream(n=40)
    s, rep = decode_mimu_bytes(data)
    assert rep.ack_present and rep.leading_bytes == 4
    assert rep.packets_read == rep.packets_kept == 40
    assert rep.checksum_failures == 0 and rep.partial_bytes == 0 and rep.missing_packets == 0
    assert np.array_equal(s.number, numbers)
    assert np.array_equal(s.raw.reshape(40, 48), raw)
    assert np.array_equal(s.ticks - s.ticks[0], stamps - stamps[0])
    assert np.allclose(s.time, (stamps - stamps[0]) / 64e6, rtol=0, atol=1e-15)
    assert rep.sha256 == hashlib.sha256(data).hexdigest()
    assert rep.jitter_max_ticks <= 16  # hand-made jitter is ±8 around 1 024 000


def test_encoder_matches_struct_packets():
    data, numbers, stamps, raw = _stream(n=5, jitter=False)
    assert encode_mimu_packets(numbers, stamps, raw.reshape(5, 8, 6)) == data


def test_timestamp_wrap_and_packet_number_wrap():
    # Stamps start 3 periods below 2^32 and packet numbers 5 below 2^16: both wrap.
    n = 30
    data, numbers, stamps, _ = _stream(n=n, first_number=65531, first_stamp=(1 << 32) - 3 * PERIOD - 17)
    s, rep = decode_mimu_bytes(data)
    assert rep.timestamp_wraps == 1 and rep.packet_number_wraps == 1
    assert rep.missing_packets == 0
    assert np.all(np.diff(s.time) > 0)
    assert np.array_equal(np.diff(s.ticks), np.diff(stamps))  # the unwrapped, un-modded steps
    assert s.number[5] == 0 and s.number[4] == 65535


def test_long_gap_across_several_timestamp_wraps():
    # 5000 packets missing (80 s > one 2^32-tick wrap of ~67 s): the packet-number step decides.
    numbers = np.concatenate((np.arange(10), 5010 + np.arange(10)))
    stamps = 7 + numbers * PERIOD
    data, *_ = _stream(n=20, numbers=numbers, stamps=stamps)
    s, rep = decode_mimu_bytes(data)
    assert rep.missing_packets == 5000 and rep.gaps == [[9, 5000]]
    assert s.time[10] - s.time[9] == pytest.approx(5001 * 0.016, abs=1e-12)


def test_checksum_failure_is_dropped_and_reported():
    data, numbers, stamps, _ = _stream(n=300)
    b = bytearray(data)
    for i in (7, 123):  # corrupt one payload byte of packets 7 and 123
        b[4 + i * 106 + 50] ^= 0x10
    s, rep = decode_mimu_bytes(bytes(b))
    assert rep.checksum_failures == 2
    assert rep.failed_packet_numbers == [int(numbers[7]), int(numbers[123])]
    assert rep.packets_kept == 298
    assert rep.missing_packets == 2  # the dropped packets leave gaps in the numbering
    assert rep.first_failure_offset == 4 + 7 * 106
    assert int(numbers[7]) not in s.number.tolist()
    assert np.array_equal(np.delete(stamps, [7, 123]) - stamps[0], s.ticks - s.ticks[0])


def test_too_many_failures_refuse_the_file():
    data, *_ = _stream(n=200)
    b = bytearray(data)
    b[4 + 10 * 106 + 20] ^= 1
    b[4 + 11 * 106 + 20] ^= 1  # 2 of 200 = 1 % — still accepted (limit is > 1 %)
    decode_mimu_bytes(bytes(b))
    b[4 + 12 * 106 + 20] ^= 1  # 3 of 200 = 1.5 %
    with pytest.raises(RecordingError, match="checksum"):
        decode_mimu_bytes(bytes(b))


def test_misaligned_stream_is_refused():
    # Issue #13 changed this contract: one lost byte no longer refuses the file (the importer
    # resynchronises; test_lost_bytes_resynchronise), but a stream misaligned so often that more
    # than 1 % of it is damaged still is.
    data, *_ = _stream(n=200)
    broken = data
    for i in (150, 100, 50):  # one byte lost in each of three packets: 3 of 200 damaged
        cut = 4 + i * 106 + 10
        broken = broken[:cut] + broken[cut + 1 :]
    with pytest.raises(RecordingError, match="misaligned"):
        decode_mimu_bytes(broken)


def test_trailing_partial_packet_is_ignored():
    data, numbers, *_ = _stream(n=20)
    s, rep = decode_mimu_bytes(data + data[4 : 4 + 83])
    assert rep.partial_bytes == 83 and rep.packets_read == 20
    assert np.array_equal(s.number, numbers)


def test_missing_ack_is_reported_not_required():
    data, numbers, *_ = _stream(n=20, ack=False)
    s, rep = decode_mimu_bytes(data)
    assert not rep.ack_present and rep.leading_bytes == 0 and rep.packets_kept == 20
    assert any("ack" in n for n in rep.notes)
    s2, rep2 = decode_mimu_bytes(b"\x01\x02\x03" + data)  # junk before the first packet
    assert rep2.leading_bytes == 3 and np.array_equal(s2.number, numbers)


@pytest.mark.parametrize("blob", [b"", b"hello world\n" * 50, bytes(range(256)) * 20, MIMU_ACK + b"\x00" * 500])
def test_not_a_mimu_stream(blob):
    with pytest.raises(RecordingError, match="not an MIMU stream"):
        decode_mimu_bytes(blob)


def test_equal_timestamps_are_refused():
    numbers = np.arange(10)
    stamps = numbers * PERIOD
    stamps[5] = stamps[4]
    data, *_ = _stream(n=10, numbers=numbers, stamps=stamps)
    with pytest.raises(RecordingError, match="timestamp"):
        decode_mimu_bytes(data)


def test_gzip_and_plain_files_agree(tmp_path):
    data, *_ = _stream(n=80)
    plain = tmp_path / "a.bin"
    plain.write_bytes(data)
    gz = tmp_path / "b.bin"  # gzip with a misleading name: told by the magic bytes
    gz.write_bytes(gzip.compress(data))
    s1, r1 = read_mimu_stream(plain)
    s2, r2 = read_mimu_stream(gz)
    assert not r1.gzipped and r2.gzipped
    assert r1.sha256 == r2.sha256 == hashlib.sha256(data).hexdigest()
    for f in ("number", "ticks", "raw"):
        assert np.array_equal(getattr(s1, f), getattr(s2, f))
    (tmp_path / "c.bin.gz").write_bytes(gzip.compress(data)[:-20])  # truncated gzip
    with pytest.raises(RecordingError, match="gzip"):
        read_mimu_stream(tmp_path / "c.bin.gz")
    with pytest.raises(FileNotFoundError):
        read_mimu_stream(tmp_path / "missing.bin")


def test_scaling_clipping_and_frames(tmp_path):
    n = 50
    rng = np.random.default_rng(5)
    raw = rng.integers(-30, 30, size=(n, 8, 6))  # a board at rest
    raw[2:5, 2, 4] = 32767  # gyro of packet-order IMU 3 at the limit for three samples
    raw[3:5, 5, 0] = -32768  # acc of IMU 6 at the limit for two samples
    raw[6:8, 1, 3] = 32766  # one code inside: not clipped
    numbers = np.arange(n)
    data = encode_mimu_packets(numbers, 5 + numbers * PERIOD, raw)
    f = tmp_path / "s.bin"
    f.write_bytes(data)
    rec, rep, st = import_mimu(f, return_report=True)
    assert np.allclose(rec.acc, raw[..., :3] * 9.80665 / 2048, rtol=1e-15)
    assert np.allclose(rec.gyro, np.deg2rad(raw[..., 3:] / 16.4), rtol=1e-14)
    assert rep.dropped == []  # every full-scale value is corroborated by its own neighbour
    assert rec.acc_clipped.sum() == 2 and rec.acc_clipped[3:5, 5].all()
    assert rec.gyro_clipped.sum() == 3 and rec.gyro_clipped[2:5, 2].all()
    assert rec.acc_range == pytest.approx(16 * 9.80665) and rec.gyro_range == pytest.approx(math.radians(2000))
    # 0.8 s cannot hold a 3 s rest: noise falls back to the preset's and the source says so.
    assert st.n_segments == 0 and "not estimated" in rec.source
    nominal = mimu4444_8()
    assert np.allclose(rec.acc_noise_std, nominal.acc_noise_std.numpy())
    assert set(rec.segment.tolist()) == {"dynamic"}


def test_source_states_provenance(tmp_path):
    data, *_ = _stream(n=30)
    f = tmp_path / "p.bin"
    f.write_bytes(data)
    rec = import_mimu(f)
    for phrase in ("p.bin", hashlib.sha256(data).hexdigest(), "30 packets read", "0 checksum failures",
                   "0 trailing partial bytes"):
        assert phrase in rec.source


# ---------------------------------------------------------------------------------------- issue #13: damaged streams
def _packets(data: bytes, ack: bool = True) -> list[bytes]:
    """The 106-byte packets of a hand-made stream, to rearrange."""
    body = data[4:] if ack else data
    return [body[i : i + 106] for i in range(0, len(body), 106)]


def _assert_kept(s, numbers, stamps, raw, keep):
    """The stream holds exactly the packets ``keep`` (indices into the hand-made fields), in order,
    with their values and their stamps' spacing."""
    assert np.array_equal(s.number, np.asarray(numbers)[keep] % 65536)
    assert np.array_equal(s.raw.reshape(len(keep), 48), raw[keep])
    assert np.array_equal(s.ticks - s.ticks[0], stamps[keep] - stamps[keep][0])


def test_swapped_adjacent_packets_are_put_back():
    data, numbers, stamps, raw = _stream(n=120)
    pk = _packets(data)
    pk[40], pk[41] = pk[41], pk[40]
    s, rep = decode_mimu_bytes(MIMU_ACK + b"".join(pk))
    _assert_kept(s, numbers, stamps, raw, np.arange(120))  # order restored, no time shifted
    assert rep.reordered == [[int(numbers[40]), 4 + 41 * 106]]  # the late one, where it arrived
    assert rep.reordered_packets == 1 and rep.missing_packets == 0 and rep.dropped == []
    assert "reordered packets put back by number (kept): 1" in str(rep)


def test_repeated_packets_are_dropped_as_duplicates():
    data, numbers, stamps, raw = _stream(n=700)
    pk = _packets(data)
    # packet 8 again two packets later, packet 50 again 550 packets later
    stream = pk[:10] + [pk[8]] + pk[10:600] + [pk[50]] + pk[600:]
    s, rep = decode_mimu_bytes(MIMU_ACK + b"".join(stream))
    _assert_kept(s, numbers, stamps, raw, np.arange(700))
    assert rep.dropped == [["duplicate", int(numbers[8]), 4 + 10 * 106], ["duplicate", int(numbers[50]), 4 + 601 * 106]]
    assert rep.duplicate_packets == 2 and rep.packets_read == 702 and rep.packets_kept == 700
    assert rep.missing_packets == 0 and rep.failed_packets == 0 and rep.reordered == []


def test_copies_that_differ_are_both_dropped():
    data, numbers, stamps, raw = _stream(n=300)
    pk = _packets(data)
    other = _packet(int(numbers[30]), int(stamps[30]), raw[30] + 1)  # same number and stamp, other values
    s, rep = decode_mimu_bytes(MIMU_ACK + b"".join(pk[:200] + [other] + pk[200:]))
    _assert_kept(s, numbers, stamps, raw, np.delete(np.arange(300), 30))
    assert rep.dropped == [["conflict", int(numbers[30]), 4 + 30 * 106], ["conflict", int(numbers[30]), 4 + 200 * 106]]
    assert rep.conflicting_packets == 2 and rep.missing_packets == 1


@pytest.mark.parametrize("edit, skipped", [("lost", 103), ("inserted", 109), ("between", 5)])
def test_lost_or_inserted_bytes_resynchronise(edit, skipped):
    data, numbers, stamps, raw = _stream(n=300)
    at = 4 + 120 * 106  # packet 120
    if edit == "lost":  # three bytes of packet 120 lost
        broken = data[: at + 37] + data[at + 40 :]
    elif edit == "inserted":  # three bytes inserted inside packet 120
        broken = data[: at + 37] + b"\x55\xaa\x64" + data[at + 37 :]
    else:  # five bytes between packets 119 and 120: no packet is damaged
        broken = data[:at] + b"\xaa\x00\x01\x64\x00" + data[at:]
    s, rep = decode_mimu_bytes(broken)
    assert rep.skipped == [[at, skipped]] and rep.bytes_skipped == skipped
    assert rep.first_failure_offset == at
    keep = np.arange(300) if edit == "between" else np.delete(np.arange(300), 120)
    _assert_kept(s, numbers, stamps, raw, keep)  # every packet after the damage kept
    assert rep.missing_packets == 300 - keep.size and rep.checksum_failures == 0
    assert rep.n_bytes == 4 + 106 * rep.packets_read + rep.bytes_skipped + rep.partial_bytes
    assert f"{skipped} bytes skipped in 1 run(s) [byte offset, length] [[{at}, {skipped}]]" in str(rep)


def test_reordering_across_both_wraps():
    # Numbers wrap 65535 → 0 between positions 4 and 5, stamps wrap 2^32 between 2 and 3; the
    # packets on both sides of each wrap arrive swapped.
    data, numbers, stamps, raw = _stream(n=40, first_number=65531, first_stamp=(1 << 32) - 3 * PERIOD - 17)
    pk = _packets(data)
    pk[2], pk[3] = pk[3], pk[2]
    pk[4], pk[5] = pk[5], pk[4]
    s, rep = decode_mimu_bytes(MIMU_ACK + b"".join(pk))
    _assert_kept(s, numbers, stamps, raw, np.arange(40))
    assert rep.timestamp_wraps == 1 and rep.packet_number_wraps == 1 and rep.missing_packets == 0
    assert [r[0] for r in rep.reordered] == [int(numbers[2]), int(numbers[4]) % 65536]  # 65533, 65535
    assert np.all(np.diff(s.ticks) > 0)


def test_far_repeat_across_the_number_wrap():
    # 70 packets from 65500: packet 65510 turns up again after the number wrapped (at 30).
    data, numbers, stamps, raw = _stream(n=70, first_number=65500)
    pk = _packets(data)
    s, rep = decode_mimu_bytes(MIMU_ACK + b"".join(pk[:67] + [pk[10]] + pk[67:]))
    _assert_kept(s, numbers, stamps, raw, np.arange(70))
    assert rep.dropped == [["duplicate", 65510, 4 + 67 * 106]] and rep.missing_packets == 0


def test_stamp_or_number_off_the_grid_is_dropped():
    n = 300
    numbers = np.arange(n)
    stamps = 5 + numbers * PERIOD + np.random.default_rng(3).integers(-4, 5, n)  # grid ± 4 ticks
    stamps[77] += 500  # 7.8 µs late: far beyond the ±8-tick jitter
    stamps[200] += 8  # within the jitter: kept (and indistinguishable from it)
    numbers = numbers.copy()
    numbers[150] = 4000  # a wrong number on a right stamp
    data, _, _, raw = _stream(n=n, numbers=numbers, stamps=stamps)
    s, rep = decode_mimu_bytes(data)
    assert rep.dropped == [["timestamp", 77, 4 + 77 * 106], ["timestamp", 4000, 4 + 150 * 106]]
    assert rep.timestamp_failures == 2 and rep.missing_packets == 2
    _assert_kept(s, numbers, stamps, raw, np.delete(np.arange(n), [77, 150]))


def test_one_wrong_number_half_the_range_away_shifts_nothing():
    # Found by the fuzz study: 37590 (0x92D6) read as 4822 (0x12D6) is −32768 + 0 and +32769
    # from its neighbours; summing the two wrapped steps lands 2^16 short, which put every later
    # packet 65 536 numbers early.
    n = 300
    numbers = 37499 + np.arange(n)
    numbers[91] = 4822
    stamps = 11 + (37499 + np.arange(n)) * PERIOD
    data, _, _, raw = _stream(n=n, numbers=numbers, stamps=stamps, span=30)
    s, rep = decode_mimu_bytes(data)
    assert rep.dropped == [["timestamp", 4822, 4 + 91 * 106]] and rep.reordered == []
    assert rep.packet_number_wraps == 0 and rep.missing_packets == 1
    _assert_kept(s, numbers, stamps, raw, np.delete(np.arange(n), 91))


def test_first_packet_stamped_late_is_kept():
    # The shared recordings' first packet sits ~0.35 ms after the grid of the others.
    numbers = np.arange(50)
    stamps = 9 + numbers * PERIOD
    stamps[0] += 22_190
    data, _, _, raw = _stream(n=50, numbers=numbers, stamps=stamps)
    s, rep = decode_mimu_bytes(data)
    assert rep.packets_kept == 50 and rep.dropped == [] and rep.first_packet_lead_ticks == 22_190
    assert rep.first_interval_ticks == PERIOD - 22_190
    stamps[0] += 20_000  # 0.66 ms: beyond FIRST_PACKET_LEAD_TICKS, so the stamp is wrong
    data, *_ = _stream(n=50, numbers=numbers, stamps=stamps)
    s, rep = decode_mimu_bytes(data, max_fail_fraction=0.05)
    assert rep.dropped == [["timestamp", 0, 4]]


def test_first_packet_keeps_its_lead_when_a_wrong_number_sorts_before_it():
    # Found by the fuzz study: a wrong number that sorts below the real first packet made that
    # one lose its exemption.
    n = 300
    numbers = 29932 + np.arange(n)
    stamps = 7 + numbers * PERIOD
    stamps[0] += 22_190
    numbers = numbers.copy()
    numbers[280] = 65284  # 30 000 below 29 932 in serial arithmetic
    data, _, _, raw = _stream(n=n, numbers=numbers, stamps=stamps, span=30)
    s, rep = decode_mimu_bytes(data)
    assert rep.dropped == [["timestamp", 65284, 4 + 280 * 106]]
    assert rep.first_packet_lead_ticks == 22_190
    _assert_kept(s, numbers, stamps, raw, np.delete(np.arange(n), 280))


def test_report_lists_are_complete_and_printed_capped():
    data, numbers, *_ = _stream(n=3000, span=30)
    b = bytearray(data)
    bad = list(range(100, 2900, 200))  # 14 checksum failures
    for i in bad:
        b[4 + i * 106 + 60] ^= 0x01
    s, rep = decode_mimu_bytes(bytes(b))
    assert rep.failed_packet_numbers == [int(numbers[i]) for i in bad]
    assert rep.dropped == [["checksum", int(numbers[i]), 4 + i * 106] for i in bad]
    assert rep.to_dict()["dropped"] == rep.dropped and rep.drop_counts["checksum"] == 14
    text = str(rep)
    assert "dropped packets by reason: checksum 14" in text and "… 4 more]" in text
    assert f"['checksum', {int(numbers[bad[10]])}," not in text  # the 11th is only in to_dict


def test_bad_checksum_in_the_last_slot_and_a_partial_tail():
    data, numbers, stamps, raw = _stream(n=150)
    b = bytearray(data + data[4 : 4 + 83])
    b[4 + 149 * 106 + 9] ^= 0x80  # the last whole packet
    s, rep = decode_mimu_bytes(bytes(b))
    assert rep.dropped == [["checksum", int(numbers[149]), 4 + 149 * 106]]
    assert rep.partial_bytes == 83 and rep.packets_read == 150 and rep.bytes_skipped == 0
    _assert_kept(s, numbers, stamps, raw, np.arange(149))


# ---------------------------------------------------------------------------------------- real data
@pytest.fixture(scope="module")
def real(mimu_dir):
    """All six experiments imported once: {name: (recording, report, static analysis, seconds)}."""
    out = {}
    for e in EXPERIMENTS:
        p = mimu_dir / e / "data.bin.gz"
        if not p.is_file():
            pytest.skip(f"{p} missing")
        t0 = _time.perf_counter()
        rec, rep, st = import_mimu(p, return_report=True)
        out[e] = (rec, rep, st, _time.perf_counter() - t0)
    return out


def test_real_import_is_fast(real):
    # "A few seconds" per experiment; generous for a shared 2-core machine.
    assert max(v[3] for v in real.values()) < 10.0


def test_real_zero_checksum_failures(real):
    for e, (rec, rep, st, _) in real.items():
        assert rep.checksum_failures == 0 and rep.header_failures == 0, e
        assert rep.packets_kept == rep.packets_read == rec.T, e
        assert rep.missing_packets == 0 and rep.ack_present, e


def test_real_nothing_flagged_but_the_exp1_tail(real):
    # Issue #13: the plausibility and stamp checks never fire on the six real recordings.
    for e, (rec, rep, st, _) in real.items():
        assert rep.dropped == [] and rep.skipped == [] and rep.reordered == [], e
        assert rep.bytes_skipped == rep.range_failures == rep.jump_failures == rep.timestamp_failures == 0, e
        assert rep.implausible == [], e  # the rigid-board bound never fires on the vigorous real motion
        assert rep.partial_bytes == (83 if e == "exp_1" else 0), e
        # the short first interval is the first packet stamped ~0.35 ms late, and is exempt
        assert 20_000 < rep.first_packet_lead_ticks < 23_000, e


def test_real_reordered_and_repeated_packets_keep_the_time_axis(mimu_dir):
    # The reproduction: exp_1 with packets 1000/1001 swapped and packet 2000 sent again
    # 500 packets later imported with every later time off by 1073.74 s.
    data = gzip.open(mimu_dir / "exp_1" / "data.bin.gz").read()
    clean, _ = decode_mimu_bytes(data)
    pk = [data[4 + i * 106 : 4 + (i + 1) * 106] for i in range((len(data) - 4) // 106)]
    pk[1000], pk[1001] = pk[1001], pk[1000]
    pk.insert(2500, pk[2000])
    s, rep = decode_mimu_bytes(MIMU_ACK + b"".join(pk) + data[-83:])
    assert np.array_equal(s.time, clean.time) and np.array_equal(s.raw, clean.raw)
    assert np.array_equal(s.number, clean.number)
    assert rep.reordered == [[int(clean.number[1000]), 4 + 1001 * 106]]
    assert rep.dropped == [["duplicate", int(clean.number[2000]), 4 + 2500 * 106]]
    assert rep.missing_packets == 0 and rep.partial_bytes == 83


def test_real_matches_published_checksums_and_sizes(real, mimu_dir):
    listed = {}
    for line in (mimu_dir / "SHA256_uncompressed.txt").read_text().split("\n"):
        if line.strip():
            name, sha, size = line.split()
            listed[name.split("/")[0]] = (sha, int(size))
    for e, (rec, rep, st, _) in real.items():
        assert (rep.sha256, rep.n_bytes) == listed[e], e
        # bytes = ack + whole packets + partial tail
        assert rep.n_bytes == 4 + 106 * rep.packets_read + rep.partial_bytes, e
    assert real["exp_1"][1].partial_bytes == 83
    assert all(real[e][1].partial_bytes == 0 for e in EXPERIMENTS[1:])


def test_real_time_axis(real):
    for e, (rec, rep, st, _) in real.items():
        dt = np.diff(rec.time)
        assert np.all(dt > 0), e
        assert rep.sample_rate_hz == pytest.approx(62.5, abs=1e-3), e
        assert 590 < rep.duration_s < 640, e
        assert rep.jitter_max_ticks <= 8, e  # README: ±8 ticks
        assert 15.6e-3 < dt[0] < 15.7e-3, e  # README: the first interval is ~15.65 ms
        assert np.all(np.abs(dt[1:] - 0.016) <= 8 / 64e6 + 1e-12), e
        assert rep.timestamp_wraps == 9, e  # ~600 s of 64 MHz ticks cross 2^32 eight or nine times


def test_real_first_packet_against_struct(real, mimu_dir):
    raw = gzip.open(mimu_dir / "exp_1" / "data.bin.gz").read(4 + 106)
    fields = struct.unpack(">BHBI48hH", raw[4:])
    vals = np.array(fields[4:52]).reshape(8, 6)
    rec = real["exp_1"][0]
    assert np.allclose(rec.acc[0], vals[:, :3] * G0 / 2048, rtol=1e-15)
    assert np.allclose(rec.gyro[0], np.deg2rad(vals[:, 3:] / 16.4), rtol=1e-14)
    assert np.allclose(ACC_SCALE, G0 / 2048) and np.allclose(GYRO_SCALE, math.pi / 180 / 16.4)


def test_real_nominal_geometry(real, mimu_dir):
    lines = [l for l in (mimu_dir / "IMU_positions.csv").read_text().splitlines() if l.strip()]
    csv = np.array([[float(v) for v in l.split(",")[1:]] for l in lines[1:4]]).T  # (8, 3)
    preset = mimu4444_8()
    assert np.allclose(csv, preset.positions.numpy(), atol=1e-12)
    C = np.array([[0, -1, 0], [-1, 0, 0], [0, 0, -1]], dtype=float)  # README: sensor → array
    for e, (rec, *_) in real.items():
        assert np.allclose(rec.nominal_position, csv, atol=1e-12), e
        q = rec.nominal_orientation
        assert np.allclose(q[0::2], [1, 0, 0, 0]) and np.allclose(q[1::2], MIMU_BOTTOM_QUAT), e
        R = quat_to_matrix(torch.as_tensor(q[1])).numpy()  # array → sensor
        assert np.allclose(R.T, C, atol=1e-15), e


def test_real_twenty_distinct_orientations(real):
    for e, (rec, rep, st, _) in real.items():
        assert st.n_orientations == 20 and rep.orientations == 20, (e, st.n_orientations)
        # Distinct orientations really are distinct (icosahedron faces ~42° apart), and rests
        # given one label really agree within 2°.
        d, lab = st.directions, st.orientation_labels
        ang = angle_deg(d[:, None], d[None])
        same = lab[:, None] == lab[None]
        assert ang[same].max() <= 2.0, e
        assert ang[~same].min() > 30.0, e


def test_real_gravity_norm_at_rest(real):
    for e, (rec, rep, st, _) in real.items():
        norm = np.linalg.norm(st.acc_means, axis=-1).mean(0)  # (K,) averaged over the rests
        assert np.all(np.abs(norm - 9.81) < 0.15), (e, norm)


def test_real_top_and_bottom_agree_in_every_rest(real):
    for e, (rec, rep, st, _) in real.items():
        m = st.acc_means  # (S, K, 3) array frame (rotated with the nominal orientations)
        top, bottom = m[:, 0::2], m[:, 1::2]
        ang = angle_deg(top[:, :, None], bottom[:, None, :])  # every top/bottom pair, every rest
        assert ang.max() < 15.0, (e, ang.max())
        # Without the bottom-side rotation they would point apart (checks the frames matter).
        raw_ang = angle_deg(rec.acc[st.segments[0][0]:st.segments[0][1]].mean(0)[0],
                            rec.acc[st.segments[0][0]:st.segments[0][1]].mean(0)[1])
        assert raw_ang > 30.0, e


def test_real_noise_estimated_from_rests(real):
    for e, (rec, rep, st, _) in real.items():
        S = st.n_segments
        assert f"noise std estimated from {S} static segments" in rec.source, e
        assert np.all((rec.acc_noise_std > 0.02) & (rec.acc_noise_std < 0.15)), e
        assert np.all((np.degrees(rec.gyro_noise_std) > 0.05) & (np.degrees(rec.gyro_noise_std) < 1.0)), e
        # Independent estimate for white noise: std of first differences / √2, per rest (written
        # out here, not taken from segments.difference_noise_std).  The accelerometers of IMUs 3
        # and 6 carry a tone (~9 Hz, ~21 Hz) in every experiment, so their pooled spread differs
        # from it by 10–45 %; the importer flags them in the report.  All others agree within 3 %.
        d = np.concatenate([np.diff(rec.acc[a:b], axis=0) for a, b in st.segments])
        white = np.sqrt((d.var(0) / 2).mean(-1))
        ok = np.array([k not in (3, 6) for k in range(8)])
        assert np.allclose(rec.acc_noise_std[ok], white[ok], rtol=0.03), (e, rec.acc_noise_std, white)
        ratio = np.array(rep.acc_whiteness_ratio)
        assert np.allclose(ratio, rec.acc_noise_std / white, rtol=1e-3), e
        assert set(np.flatnonzero(np.abs(ratio - 1) > 0.05).tolist()) == {3, 6}, (e, ratio)
        assert any(n.startswith("acc rest noise not white") and "IMU 3" in n and "IMU 6" in n for n in rep.notes), e


def test_real_segments_and_clipping(real):
    for e, (rec, rep, st, _) in real.items():
        assert set(np.unique(rec.segment)) == {"static", "dynamic"}, e
        static = rec.segment == "static"
        assert 0.7 < static.mean() < 0.85, e
        assert all((b - a) * 0.016 >= 3.0 for a, b in st.segments), e
        # Clipping happens in the vigorous motion only, at the int16 codes.
        assert not rec.gyro_clipped[static].any() and not rec.acc_clipped[static].any(), e
        assert 0.006 < rec.gyro_clipped.mean() < 0.035, e
        codes = np.rint(rec.gyro / GYRO_SCALE)
        assert np.array_equal(rec.gyro_clipped, ((codes == 32767) | (codes == -32768)).any(-1)), e
        assert rec.acc_clipped.mean() < 1e-3, e


# ---------------------------------------------------------------------------------------- io and CLI
def test_real_write_read_roundtrip(real, tmp_path):
    io = pytest.importorskip("accel_bayes.data.io")
    rec = real["exp_1"][0]
    path = tmp_path / "rec.nc"
    io.write_recording(rec, path)
    back = io.read_recording(path)
    for f in ("time", "acc", "gyro", "nominal_position", "nominal_orientation", "acc_noise_std",
              "gyro_noise_std", "acc_clipped", "gyro_clipped"):
        assert np.array_equal(getattr(back, f), getattr(rec, f)), f
    assert back.segment.astype(str).tolist() == rec.segment.tolist()
    for f in ("reference_imu", "acc_range", "gyro_range", "description", "source"):
        assert getattr(back, f) == getattr(rec, f), f
    assert back.attrs.get("import_report") == rec.attrs["import_report"]


def test_cli_errors_exit_2(tmp_path, capsys):
    from accel_bayes.cli import main

    assert main(["import-mimu", str(tmp_path / "missing.bin.gz"), "-o", str(tmp_path / "r.nc")]) == 2
    junk = tmp_path / "junk.bin"
    junk.write_bytes(b"not a stream" * 100)
    assert main(["import-mimu", str(junk), "-o", str(tmp_path / "r.nc")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 2 and "not an MIMU stream" in err[1]
    assert not (tmp_path / "r.nc").exists()


def test_cli_imports_a_file(tmp_path, capsys, mimu_dir):
    io = pytest.importorskip("accel_bayes.data.io")
    from accel_bayes.cli import main

    out = tmp_path / "exp_3.nc"
    assert main(["import-mimu", str(mimu_dir / "exp_3" / "data.bin.gz"), "-o", str(out)]) == 0
    text = capsys.readouterr().out
    for phrase in ("checksum failures: 0", "static segments: 20", "distinct orientations: 20", "clipped"):
        assert phrase in text
    rec = io.read_recording(out)
    assert rec.T == 37541 and rec.K == 8
    assert main(["import-mimu", str(mimu_dir / "exp_3" / "data.bin.gz"), "-o", str(out)]) == 2  # exists
    assert "exists" in capsys.readouterr().err
    small = tmp_path / "small.bin"
    small.write_bytes(_stream(n=40)[0])
    assert main(["import-mimu", str(small), "-o", str(out), "--overwrite"]) == 0
    assert io.read_recording(out).T == 40

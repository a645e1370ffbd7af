"""What reading a MIMU4444 stream found (:class:`ImportReport`): counts, and every dropped,
skipped and reordered packet by reason, packet number and byte offset.

Filled by :func:`accel_bayes.data.mimu_decode.decode_mimu_bytes` (the packets) and
:func:`accel_bayes.data.mimu.recording_from_stream` (rests, clipping, noise whiteness); printed
by ``accel-bayes import-mimu`` and stored whole in the recording's ``import_report`` attribute.
"""
from __future__ import annotations

from dataclasses import asdict, dataclass, field

from .mimu_packets import TICK_HZ

__all__ = ["DROP_REASONS", "ImportReport"]

DROP_REASONS = ("checksum", "header", "timestamp", "duplicate", "conflict", "range", "jump")

_MAX_LISTED = 10  # entries of a list printed in the text report (to_dict holds them all)


@dataclass
class ImportReport:
    """What reading a MIMU stream found.  All counts are exact and every list is complete
    (:meth:`lines` prints the first few entries of each)."""

    file: str = ""
    sha256: str = ""  # of the decompressed stream
    gzipped: bool = False
    n_bytes: int = 0  # decompressed
    ack_present: bool = False
    leading_bytes: int = 0  # bytes before the first packet (4 when the ack is present)
    packets_read: int = 0  # complete 106-byte packets: the framed ones plus those damaged in place
    packets_kept: int = 0
    checksum_failures: int = 0
    header_failures: int = 0  # wrong header byte or payload size (checksum may be fine)
    failed_packet_numbers: list = field(default_factory=list)  # as read from the failing packets
    first_failure_offset: int | None = None  # byte offset of the first dropped (not duplicate) packet or skipped byte
    partial_bytes: int = 0
    bytes_skipped: int = 0  # lost/inserted bytes passed over to resynchronise (not partial, not leading)
    skipped: list = field(default_factory=list)  # [byte offset, length] of every skipped run
    duplicate_packets: int = 0
    timestamp_failures: int = 0  # stamp disagrees with its neighbours' grid (> TIME_TOL_TICKS without gaps)
    conflicting_packets: int = 0  # copies of one packet number with different bytes (all dropped)
    range_failures: int = 0  # one IMU alone off the board's consensus
    jump_failures: int = 0  # one IMU alone jumping in one sample
    # [packet number, byte offset, IMU, "acc"/"gyro", "range"/"jump", |deviation| / bound] of every
    # IMU sensor the rigid-board check rejected (its packet is dropped)
    implausible: list = field(default_factory=list)
    reordered_packets: int = 0  # arrived after a higher packet number; put back in place and kept
    dropped: list = field(default_factory=list)  # [reason, packet number, byte offset] of every drop
    reordered: list = field(default_factory=list)  # [packet number, byte offset] of every reordered packet
    missing_packets: int = 0  # gaps in the packet numbers of the kept packets
    gaps: list = field(default_factory=list)  # [after packet number, how many missing]
    packet_number_wraps: int = 0
    timestamp_wraps: int = 0
    first_packet_lead_ticks: float = 0.0  # how late the first packet sits after the others' grid
    duration_s: float = 0.0
    sample_rate_hz: float = float("nan")
    period_median_ticks: float = float("nan")
    jitter_std_ticks: float = float("nan")  # std of the 1-step intervals, first excluded
    jitter_max_ticks: float = float("nan")  # max |interval − median|, first excluded
    first_interval_ticks: float = float("nan")
    # Filled by import_mimu:
    static_segments: int | None = None
    orientations: int | None = None
    static_fraction: float | None = None
    acc_clipped_fraction: float | None = None
    gyro_clipped_fraction: float | None = None
    acc_whiteness_ratio: list | None = None  # per IMU: pooled rest std / first-difference std
    gyro_whiteness_ratio: list | None = None
    notes: list = field(default_factory=list)

    @property
    def failed_packets(self) -> int:
        """Packets dropped for any reason but duplication (checksum, header, timestamp,
        conflict, range, jump)."""
        return self.packets_read - self.packets_kept - self.duplicate_packets

    @property
    def drop_counts(self) -> dict:
        """{reason: packets dropped for it}, reasons as in :data:`DROP_REASONS`."""
        out = dict.fromkeys(DROP_REASONS, 0)
        for reason, *_ in self.dropped:
            out[reason] += 1
        return out

    def to_dict(self) -> dict:
        return asdict(self)

    def lines(self) -> list[str]:
        """A short human report (what ``accel-bayes import-mimu`` prints)."""
        out = [
            f"file: {self.file} ({'gzip, ' if self.gzipped else ''}{self.n_bytes} bytes, sha256 {self.sha256[:16]}…)",
            f"command ack A0 28 00 C8: {'present' if self.ack_present else 'ABSENT'}"
            + (f" ({self.leading_bytes} leading bytes skipped)" if not self.ack_present and self.leading_bytes else ""),
            f"packets: {self.packets_read} read, {self.packets_kept} kept; checksum failures: {self.checksum_failures}"
            + (f" (packet numbers {_capped(self.failed_packet_numbers)})" if self.checksum_failures else "")
            + (f"; header/size failures: {self.header_failures}" if self.header_failures else ""),
            f"trailing partial packet: {self.partial_bytes} bytes ignored",
            f"missing packet numbers: {self.missing_packets}" + (f" in {len(self.gaps)} gap(s)" if self.missing_packets else "")
            + (f"; duplicates dropped: {self.duplicate_packets}" if self.duplicate_packets else ""),
        ]
        if self.bytes_skipped:
            out.append(f"resynchronised: {self.bytes_skipped} bytes skipped in {len(self.skipped)} run(s) "
                       f"[byte offset, length] {_capped(self.skipped)}")
        if self.reordered_packets:
            out.append(f"reordered packets put back by number (kept): {self.reordered_packets} "
                       f"[number, byte offset] {_capped(self.reordered)}")
        counts = {k: v for k, v in self.drop_counts.items() if v}
        if counts:
            out.append("dropped packets by reason: " + ", ".join(f"{k} {v}" for k, v in counts.items())
                       + f"; [reason, number, byte offset] {_capped(self.dropped)}")
        if self.implausible:
            out.append(f"implausible values (rigid-board check; packets dropped): {len(self.implausible)} "
                       f"[number, byte offset, IMU, sensor, test, deviation/bound] {_capped(self.implausible)}")
        out.append(
            f"duration: {self.duration_s:.2f} s at {self.sample_rate_hz:.3f} Hz "
            f"(period {self.period_median_ticks / TICK_HZ * 1e3:.4f} ms, jitter std {self.jitter_std_ticks:.2f} ticks, "
            f"max {self.jitter_max_ticks:.0f} ticks; first interval {self.first_interval_ticks / TICK_HZ * 1e3:.3f} ms)"
        )
        if self.static_segments is not None:
            out.append(
                f"static segments: {self.static_segments} ({100 * self.static_fraction:.1f} % of samples), "
                f"distinct orientations: {self.orientations}"
            )
        if self.acc_clipped_fraction is not None:
            out.append(
                f"clipped samples: acc {100 * self.acc_clipped_fraction:.3f} %, gyro {100 * self.gyro_clipped_fraction:.3f} %"
            )
        out.extend(f"note: {n}" for n in self.notes)
        return out

    def __str__(self) -> str:
        return "\n".join(self.lines())


def _capped(items: list) -> str:
    """The first few entries of a report list, and how many more the full report holds."""
    head = ", ".join(str(x) for x in items[:_MAX_LISTED])
    return f"[{head}{f', … {len(items) - _MAX_LISTED} more' if len(items) > _MAX_LISTED else ''}]"

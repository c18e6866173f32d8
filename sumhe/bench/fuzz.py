"""Fuzzing the input decoders: NMEA lines through :class:`~sumhe.io.nmea.NmeaDecoder`, ``candump -L`` lines through
the CAN log reader and :class:`~sumhe.io.can.CanDecoder` (the reference vehicle's DBC and mapping).

Lines come from a seeded ``random.Random``: well-formed sentences and frames whose fields are replaced by extreme or
wrong values (``1e308``, ``nan``, 20-digit integers, text) and re-checksummed, so they reach the field decoders and
the plausibility limits; the same with a few bytes mutated (mostly checksum errors and garbled lines); random bytes.
CAN lines name the mapped ids often, with payloads of 0-64 bytes (classic and FD), valid end-to-end CRCs on some,
remote and error frames. The hypothesis tests (``tests/test_fuzz.py``) draw the ``Random``; ``sumhe bench fuzz``
runs 10^6 lines and prints lines/s and the crashes (an exception out of a decoder: there must be none).

What counts as correct (:func:`nmea_problems`, :func:`can_problems`): every fix either valid with a position in
range and every value within :data:`sumhe.io.nmea.LIMITS`, or not valid and without a position; every CAN sample
finite, of a known quantity; and the counters account for every input (NMEA fragments are sentences, checksum errors
or garbled; CAN lines are frames or malformed, frames are unused, FD, error, remote or of a mapped message).
"""

from __future__ import annotations

import datetime as dt
import math
import os
import random
import tempfile
import time
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass, field
from pathlib import Path

from sumhe.io.can import CanDecoder, DecodeStats, LogStats, read_log, reference_config
from sumhe.io.checksum import protect
from sumhe.io.nmea import LIMITS, NmeaCounters, NmeaDecoder
from sumhe.io.nmea_format import nmea_checksum
from sumhe.messages import CAN_QUANTITIES, CanSample, GnssFix, Sample

SEED_SENTENCES = (
    "GPGGA,101500.00,5004.5305762,N,01426.2660143,E,1,11,0.95,203.509,M,45.000,M,,",
    "GNGNS,101500.00,5004.5305762,N,01426.2660143,E,AAN,11,0.9,203.5,45.0,,,V",
    "GPRMC,101500.00,A,5004.5305762,N,01426.2660143,E,12.070,271.5,010626,,,A",
    "GPGLL,5004.5305762,N,01426.2660143,E,101500.00,A,D",
    "GPGST,101500.00,1.000,1.000,1.000,0.000,1.000,1.000,1.500",
    "GPZDA,101500.00,01,06,2026,00,00",
    "GPVTG,271.5,T,,M,12.070,N,22.354,K,A",
    "GNGSA,A,3,05,12,19,24,,,,,,,,,1.60,0.95,1.29",
    "GPHDT,271.5,T",
    "GNTHS,271.5,A",
    "GPGSV,3,1,11,05,45,120,40,12,30,200,38,19,60,310,44,24,10,050,30",
)
"""Well-formed sentence bodies (between ``$`` and ``*``) of every type the decoder reads, and one it does not; the
time ``101500.00`` and date ``010626`` are replaced by the line's."""

EXTREMES = (
    "", "0", "-0", "1e308", "-1e308", "1e9", "-1", "nan", "inf", "-inf", "99999999999999999999", "0.000001",
    "9999.99", "5960.0", "18001", "-1001", "A", "V", "N", "x", "1,2", "12:00", "999999", "320299", "2099",
)  # fmt: skip
"""Field values a receiver should never send (or sends when broken)."""

MAPPED_IDS = (0x130, 0x1A0, 0x1B0, 0x0C2)
"""The reference DBC's ids mapped by the reference config (yaw rate, speed, wheel speeds, steering)."""

_T0 = 1780300800.0


def _mutate(data: bytearray, rng: random.Random) -> None:
    for _ in range(rng.randint(1, 4)):
        i = rng.randint(0, len(data))
        if i == len(data) or rng.random() < 0.3:
            data.insert(i, rng.randrange(256))
        elif rng.random() < 0.5:
            data[i] = rng.randrange(256)
        else:
            del data[i]


def nmea_line(rng: random.Random, t: float) -> bytes:
    """One NMEA log line: a seed sentence with fields replaced (re-checksummed), perhaps mutated, or random bytes;
    with a receive-time prefix ``(t)`` most of the time."""
    kind = rng.random()
    if kind < 0.05:
        return bytes(rng.randrange(256) for _ in range(rng.randint(0, 90)))
    stamp = dt.datetime.fromtimestamp(t, dt.timezone.utc)
    body = rng.choice(SEED_SENTENCES).replace("101500.00", stamp.strftime("%H%M%S.%f")[:9])
    fields = body.replace("010626", stamp.strftime("%d%m%y")).split(",")
    for _ in range(rng.randint(0, 4)):
        fields[rng.randrange(1, len(fields))] = rng.choice(EXTREMES)
    body = ",".join(fields)
    line = bytearray(f"${body}*{nmea_checksum(body)}".encode("latin-1"))
    if kind < 0.25:
        _mutate(line, rng)
    prefix = f"({t:.3f}) ".encode() if rng.random() < 0.9 else b""
    return prefix + bytes(line)


def candump_line(rng: random.Random, t: float) -> str:
    """One ``candump -L`` line: a classic, FD, remote or error frame on a mapped id (often) or any id, with a
    payload of 0-64 bytes (a valid end-to-end CRC on some); or a garbled line."""
    kind = rng.random()
    if kind < 0.03:
        return "".join(chr(rng.randrange(32, 127)) for _ in range(rng.randint(0, 60)))
    can_id = rng.choice(MAPPED_IDS) if rng.random() < 0.7 else rng.randrange(0x800)
    ident = f"{can_id:03X}" if rng.random() < 0.9 else f"{rng.randrange(0x20000000):08X}"
    if kind < 0.06:
        return f"({t:.6f}) can0 {ident}#R"
    if kind < 0.08:
        return f"({t:.6f}) can0 2000{can_id:04X}#0000000000000000"  # an error frame (CAN_ERR_FLAG in the id)
    n = 8 if rng.random() < 0.6 else rng.choice((0, 1, 3, 7, 9, 12, 16, 20, 32, 48, 64))
    payload = bytes(rng.randrange(256) for _ in range(n))
    if n >= 2 and rng.random() < 0.5:
        payload = protect(payload)
    if (n > 8 and rng.random() < 0.7) or rng.random() < 0.03:
        return f"({t:.6f}) can0 {ident}##{rng.randrange(16):X}{payload.hex().upper()}"
    return f"({t:.6f}) can0 {ident}#{payload.hex().upper()}"


def nmea_problems(fixes: Sequence[GnssFix], counters: NmeaCounters) -> list[str]:
    """What is wrong with a decoder's output: fixes with values out of range or not finite, counters that do not
    account for every fragment (empty when all is well)."""
    out = []
    c = counters
    if c.fragments != c.sentences + c.checksum_errors + c.garbled:
        out.append(f"counters do not add up: {c.summary()}")
    if len(fixes) != c.fixes:
        out.append(f"{len(fixes)} fixes out, {c.fixes} counted")
    for f in fixes:
        if not math.isfinite(f.t):
            out.append(f"fix time not finite: {f}")
        if f.valid != (f.lat_deg is not None and f.lon_deg is not None):
            out.append(f"valid without a position, or a position without valid: {f}")
        lat, lon = f.lat_deg, f.lon_deg
        if lat is not None and lon is not None and not (-90.0 <= lat <= 90.0 and -180.0 <= lon <= 180.0):
            out.append(f"position out of range: {f}")
        for name, (low, high) in LIMITS.items():
            value = getattr(f, name)
            if value is not None and not low <= value <= high:
                out.append(f"{name} = {value} outside {low, high}: {f}")
        for angle in (f.course_rad, f.heading_rad):
            if angle is not None and not 0.0 <= angle < 2.0 * math.pi:
                out.append(f"angle out of range: {f}")
    return out


def can_problems(samples: Sequence[Sample], stats: DecodeStats, log_stats: LogStats, lines: int) -> list[str]:
    """What is wrong with the CAN side's output: samples not finite or of unknown quantities, lines or frames not
    accounted for (``lines`` non-blank lines were read)."""
    out = []
    if log_stats.frames + log_stats.malformed != lines:
        out.append(f"{lines} lines, {log_stats.frames} frames + {log_stats.malformed} malformed")
    if log_stats.error:
        out.append(f"the read ended early: {log_stats.error}")
    routed = sum(stats.per_message.values())
    if stats.frames != stats.unused + stats.fd_frames + stats.error_frames + stats.remote_frames + routed:
        out.append(f"frames not accounted for: {stats}")
    for s in samples:
        if not isinstance(s, CanSample) or s.quantity not in CAN_QUANTITIES or not math.isfinite(s.value):
            out.append(f"bad sample: {s}")
    return out


@dataclass
class FuzzReport:
    """One fuzz run: lines fed, crashes (exceptions out of a decoder; the first few kept), problems found in the
    output (:func:`nmea_problems`, :func:`can_problems`), fixes and samples out, seconds spent decoding."""

    nmea_lines: int = 0
    can_lines: int = 0
    crashes: int = 0
    first_crashes: list[str] = field(default_factory=list)
    problems: list[str] = field(default_factory=list)
    fixes: int = 0
    valid_fixes: int = 0
    samples: int = 0
    nmea_s: float = 0.0
    can_s: float = 0.0
    nmea_counters: NmeaCounters = field(default_factory=NmeaCounters)
    can_stats: DecodeStats = field(default_factory=DecodeStats)

    def crashed(self, where: str, err: BaseException) -> None:
        self.crashes += 1
        if len(self.first_crashes) < 5:
            self.first_crashes.append(f"{where}: {type(err).__name__}: {err}")


def fuzz_nmea(lines: Iterable[bytes], report: FuzzReport) -> list[GnssFix]:
    """Feed ``lines`` to one decoder, line by line (a crash is counted and decoding goes on); the fixes out."""
    dec = NmeaDecoder()
    fixes: list[GnssFix] = []
    start = time.perf_counter()
    for line in lines:
        report.nmea_lines += 1
        try:
            fixes.extend(dec.feed(line))
        except Exception as e:  # what this counts: there must be none
            report.crashed(f"NMEA line {line!r}", e)
    try:
        fixes.extend(dec.flush())
    except Exception as e:
        report.crashed("NMEA flush", e)
    report.nmea_s += time.perf_counter() - start
    report.fixes += len(fixes)
    report.valid_fixes += sum(f.valid for f in fixes)
    report.problems += nmea_problems(fixes, dec.counters)
    report.nmea_counters = dec.counters
    return fixes


def fuzz_candump(lines: Sequence[str], report: FuzzReport, directory: Path) -> list[Sample]:
    """Write ``lines`` as a candump log in ``directory``, read and decode it (a crash is counted); the samples."""
    path = directory / "fuzz.log"
    path.write_text("\n".join(lines) + "\n", encoding="latin-1")
    decoder = CanDecoder.from_config(reference_config())
    log_stats = LogStats()
    samples: list[Sample] = []
    start = time.perf_counter()
    try:
        for msg in read_log(path, log_stats):
            samples.extend(decoder.decode(msg))
        samples.extend(decoder.flush())
    except Exception as e:  # what this counts: there must be none
        report.crashed("candump", e)
    report.can_s += time.perf_counter() - start
    report.can_lines += len(lines)
    report.samples += len(samples)
    report.problems += can_problems(samples, decoder.stats, log_stats, sum(bool(x.strip()) for x in lines))
    report.can_stats = decoder.stats
    return samples


def generate(rng: random.Random, n: int, line: Callable[[random.Random, float], bytes | str]) -> list:
    """``n`` lines of one kind, their times 0.05 s apart (with a jump back or forward now and then)."""
    out, t = [], _T0
    for _ in range(n):
        t += 0.05 if rng.random() < 0.99 else rng.choice((-5.0, 100.0, -1e6))
        out.append(line(rng, t))
    return out


def run(lines: int, seed: int = 0, chunk: int = 100_000, progress: Callable[[str], None] | None = None) -> FuzzReport:
    """Fuzz both decoders with ``lines`` lines in all, half NMEA and half candump, in chunks of ``chunk`` lines
    (one decoder per chunk)."""
    rng = random.Random(seed)
    report = FuzzReport()
    with tempfile.TemporaryDirectory(prefix="sumhe-fuzz-") as tmp:
        done = 0
        while done < lines:
            n = min(chunk, lines - done)
            fuzz_nmea(generate(rng, n // 2, nmea_line), report)
            fuzz_candump(generate(rng, n - n // 2, candump_line), report, Path(tmp))
            done += n
            if progress is not None:
                progress(f"{done} lines, {report.crashes} crashes")
    return report


def lines(report: FuzzReport, seed: int) -> list[str]:
    """The printed result."""
    r = report
    total_s = r.nmea_s + r.can_s
    nc, cs = r.nmea_counters, r.can_stats
    out = [
        f"fuzz: {r.nmea_lines + r.can_lines} lines (seed {seed}) in {total_s:.1f} s of decoding: "
        f"{(r.nmea_lines + r.can_lines) / total_s:,.0f} lines/s; {r.crashes} crashes, {len(r.problems)} problems",
        f"NMEA: {r.nmea_lines} lines, {r.nmea_lines / r.nmea_s:,.0f} lines/s; {r.fixes} fixes ({r.valid_fixes} "
        f"valid); last chunk's counters: {nc.summary()}",
        f"candump: {r.can_lines} lines, {r.can_lines / r.can_s:,.0f} lines/s (read + decode); {r.samples} samples; "
        f"last chunk: frames {cs.frames}, decoded {cs.decoded}, unused {cs.unused}, FD {cs.fd_frames}, too long "
        f"{cs.long_frames}, short or undecodable {cs.decode_errors}, CRC errors {cs.crc_errors}, stale {cs.stale}",
        f"machine: {os.cpu_count()} CPUs (shared: figures are noisy)",
    ]
    out += [f"crash: {c}" for c in r.first_crashes]
    out += [f"problem: {p}" for p in r.problems[:5]]
    return out

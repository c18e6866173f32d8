"""Bad input that parses (issue 15, item 4): implausible NMEA values, FD and over-long CAN frames on classic
messages, a clock jump inside a CAN log, and a replay with nothing usable (the last two through ``sumhe replay`` in a
subprocess, on a simulated drive's files)."""

from __future__ import annotations

import datetime as dt
import json
import os
import subprocess
import sys
from pathlib import Path

import can
import pytest

from sumhe.io.can import CanDecoder, LogStats, read_log, reference_config
from sumhe.io.nmea import MAX_DATE_OFFSET_S, NmeaCounters, NmeaDecoder, rebase_receive_times
from sumhe.io.nmea_format import sentence
from sumhe.messages import GnssFix

from canframes import speed_frame
from loggerframes import write_log

ENV = {**os.environ, "OPENBLAS_NUM_THREADS": "1", "OMP_NUM_THREADS": "1"}


def gga(hhmmss: str, alt: str = "545.4", hdop: str = "0.9") -> str:
    return sentence(f"GPGGA,{hhmmss}.00,4807.038,N,01131.000,E,1,08,{hdop},{alt},M,46.9,M,,")


def rmc(hhmmss: str, date: str = "170524", knots: str = "10.0") -> str:
    return sentence(f"GPRMC,{hhmmss}.00,A,4807.038,N,01131.000,E,{knots},84.4,{date},,,A")


def zda(hhmmss: str, year: int) -> str:
    return sentence(f"GPZDA,{hhmmss}.00,17,05,{year},00,00")


def decode(lines: list[str]) -> tuple[list, NmeaDecoder]:
    dec = NmeaDecoder()
    fixes = [f for line in lines for f in dec.feed(line)] + dec.flush()
    return fixes, dec


def test_an_implausible_speed_altitude_or_hdop_is_ignored_and_counted_the_position_kept():
    fixes, dec = decode([gga("120000", alt="1e308", hdop="1e308"), rmc("120000", knots="1000000000")])
    (fix,) = fixes
    assert fix.valid and fix.lat_deg == pytest.approx(48 + 7.038 / 60)
    assert (fix.alt_m, fix.hdop, fix.speed_mps) == (None, None, None)
    assert dec.counters.implausible == 3 and dec.counters.garbled == 0 and dec.counters.sentences == 2


def test_values_at_the_limits_are_kept():
    fixes, dec = decode([gga("120000", alt="17999", hdop="99.9"), rmc("120000", knots="999")])
    assert (fixes[0].alt_m, fixes[0].hdop) == (17999.0, 99.9)
    assert fixes[0].speed_mps == pytest.approx(999 * 1852 / 3600)
    assert dec.counters.implausible == 0


def test_a_zda_year_2099_is_ignored_and_costs_no_epoch():
    lines = []
    for s in range(6):
        hhmmss = f"1200{s:02d}"
        lines += [zda(hhmmss, 2099), gga(hhmmss)] if s == 2 else [gga(hhmmss), rmc(hhmmss)]
    fixes, dec = decode(lines)
    assert [f.time_utc.isoformat() for f in fixes] == [f"2024-05-17T12:00:{s:02d}+00:00" for s in range(6)]
    assert dec.counters.implausible == 1 and dec.counters.backwards == 0


def test_a_date_far_from_the_receive_time_is_ignored_but_one_near_it_is_followed():
    """A receiver whose date really changed (near its own receive time) is followed at once."""
    rx0 = 1715947200.0  # 2024-05-17 12:00:00 UTC
    dec = NmeaDecoder()
    first = dec.feed(f"({rx0 + 0.1:.3f}) {gga('120000')}") + dec.feed(f"({rx0 + 0.1:.3f}) {rmc('120000')}")
    later = rx0 + 3 * MAX_DATE_OFFSET_S + 1  # the log goes on three days later: the receive time agrees with the date
    fixes = first + dec.feed(f"({later:.3f}) {gga('120001')}") + dec.feed(f"({later:.3f}) {rmc('120001', '200524')}")
    fixes += dec.flush()
    assert [f.time_utc.day for f in fixes] == [17, 20] and dec.counters.implausible == 0


def test_the_date_given_to_the_decoder_does_not_judge_the_receivers_dates():
    dec = NmeaDecoder(date=dt.date(2020, 1, 1))
    fixes = dec.feed(gga("120000")) + dec.feed(gga("120001")) + dec.feed(rmc("120001")) + dec.flush()
    assert [f.time_utc.date().isoformat() for f in fixes] == ["2020-01-01", "2024-05-17"]
    assert dec.counters.implausible == 0


def test_a_persistent_new_date_is_followed_after_a_few_epochs():
    lines = [gga("120000"), rmc("120000")]
    lines += [x for s in range(1, 6) for x in (gga(f"1200{s:02d}"), rmc(f"1200{s:02d}", date="170530"))]
    fixes, dec = decode(lines)
    years = [f.time_utc.year for f in fixes]
    assert years[0] == 2024 and years[-1] == 2030 and dec.counters.implausible == 2


def test_fd_and_over_long_frames_of_classic_messages_in_a_candump_log_are_refused(tmp_path):
    good = speed_frame(1780300800.0, 36.0, 0)
    long_payload = bytes(good.data) + bytes(56)
    log = tmp_path / "drive.log"
    log.write_text(
        f"(1780300800.000000) can0 1A0#{bytes(good.data).hex().upper()}\n"
        f"(1780300800.010000) can0 1A0#{long_payload.hex().upper()}\n"  # 64 bytes without the FD mark
        f"(1780300800.020000) can0 1A0##0{long_payload.hex().upper()}\n"  # a CAN FD frame
        f"(1780300800.030000) can0 1A0#{bytes(good.data).hex().upper()}00\n"  # 9 bytes on an 8-byte message
    )
    decoder = CanDecoder.from_config(reference_config())
    samples = [s for msg in read_log(log, LogStats()) for s in decoder.decode(msg)]
    assert [(s.quantity, s.value) for s in samples] == [("speed", pytest.approx(10.0))]
    assert (decoder.stats.fd_frames, decoder.stats.long_frames, decoder.stats.decoded) == (1, 2, 1)


def test_sumhe_candump_reports_the_refused_frames(tmp_path):
    good = bytes(speed_frame(0.0, 36.0, 0).data).hex().upper()
    log = tmp_path / "drive.log"
    log.write_text(
        f"(1780300800.000000) can0 1A0#{good}\n(1780300800.010000) can0 1A0#{good + '00' * 56}\n"
        f"(1780300800.020000) can0 1A0##1{good + '00' * 56}\n(1780300800.030000) can0 1A0##A{good}\n"
    )
    result = subprocess.run(
        [sys.executable, "-m", "sumhe", "candump", str(log)], env=ENV, capture_output=True, text=True, timeout=60
    )
    assert result.returncode == 0 and len(result.stdout.splitlines()) == 1
    assert "FD frames on classic ids 1, too long for their message 1" in result.stderr
    assert "malformed log lines 1" in result.stderr


def test_fd_and_over_long_frames_in_an_mf4_log_are_refused(tmp_path):
    good = speed_frame(1780300800.0, 36.0, 0)
    long_payload = bytes(good.data) + bytes(56)
    frames = [good]
    for i, fd in enumerate((True, False), 1):
        frames.append(
            can.Message(
                timestamp=good.timestamp + 0.01 * i,
                arbitration_id=0x1A0,
                is_extended_id=False,
                is_fd=fd,
                data=long_payload,
                channel=0,
            )
        )
    path = write_log(tmp_path / "drive.mf4", frames)
    decoder = CanDecoder.from_config(reference_config())
    samples = [s for msg in read_log(path, LogStats()) for s in decoder.decode(msg)]
    assert [s.quantity for s in samples] == ["speed"]
    assert decoder.stats.fd_frames + decoder.stats.long_frames == 2 and decoder.stats.decoded == 1


@pytest.fixture(scope="module")
def drive(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("drive")
    subprocess.run(
        [sys.executable, "-m", "sumhe", "simulate", "--out", str(out), "--duration", "40", "--seed", "3"],
        check=True,
        env=ENV,
        capture_output=True,
    )
    return out


def replay(drive: Path, can_log: Path, nmea_log: Path) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, "-m", "sumhe", "replay", str(can_log), "--nmea", str(nmea_log), "--estimator", "ekf"],
        env=ENV,
        capture_output=True,
        text=True,
        timeout=120,
    )


def test_a_one_hour_clock_jump_in_the_can_log_is_re_based_and_loses_no_output(drive, tmp_path):
    lines = (drive / "drive.log").read_text().splitlines()
    half = len(lines) // 2

    def later(line: str) -> str:
        stamp, rest = line[1:].split(")", 1)
        return f"({float(stamp) + 3600.0:.6f}){rest}"

    jumped = tmp_path / "jumped.log"
    jumped.write_text("\n".join(lines[:half] + [later(x) for x in lines[half:]]) + "\n")
    plain, moved = replay(drive, drive / "drive.log", drive / "drive.nmea"), replay(drive, jumped, drive / "drive.nmea")
    assert plain.returncode == 0 and moved.returncode == 0, moved.stderr
    a = [json.loads(x) for x in plain.stdout.splitlines()]
    b = [json.loads(x) for x in moved.stdout.splitlines()]
    assert len(a) > 1000 and len(b) == len(a)
    assert max(abs(x["lat"] - y["lat"]) for x, y in zip(a, b, strict=True)) < 1e-5  # within a metre
    assert "clock jumps by +3600.0" in moved.stderr and "clock re-based 1 times" in moved.stderr
    assert "clock resets 0" in moved.stderr


def shifted_after(lines: list[str], t_jump: float, by_s: float) -> list[str]:
    """Log lines ``(t) ...`` with ``by_s`` added to the times from ``t_jump`` on (the logger's clock stepped)."""
    out = []
    for line in lines:
        stamp, rest = line[1:].split(")", 1)
        t = float(stamp)
        out.append(f"({t + by_s if t >= t_jump else t:.6f}){rest}")
    return out


def test_a_host_clock_step_in_both_logs_is_re_based_in_both(drive, tmp_path):
    """The logger's clock steps by 1 h mid-drive (both logs stamped by it); the NMEA receive times are re-based on
    the receiver's UTC, the CAN frames on their own timeline: the output is the plain replay's."""
    can_lines = (drive / "drive.log").read_text().splitlines()
    t_jump = float(can_lines[len(can_lines) // 2][1:].split(")")[0])
    for name in ("drive.log", "drive.nmea"):
        lines = (drive / name).read_text().splitlines()
        (tmp_path / name).write_text("\n".join(shifted_after(lines, t_jump, 3600.0)) + "\n")
    plain = replay(drive, drive / "drive.log", drive / "drive.nmea")
    moved = replay(drive, tmp_path / "drive.log", tmp_path / "drive.nmea")
    assert moved.returncode == 0, moved.stderr
    a, b = plain.stdout.splitlines(), moved.stdout.splitlines()
    assert len(a) > 1000 and abs(len(b) - len(a)) <= 2, moved.stderr
    assert "drive.nmea: the log's clock jumps by +3600" in moved.stderr and "clock resets 0" in moved.stderr


def test_a_pause_of_both_logs_keeps_its_times_and_restarts_the_estimator(drive, tmp_path):
    """The logger and the receiver were off for 2 h (the receiver's UTC moved too): the CAN log's step is a pause,
    not its clock jumping (the NMEA log resumes there as well), so no log is re-based and the second part's
    estimates keep their own times, restarted once (the estimator starts over at the first fix after the gap)."""
    later = tmp_path / "later"
    text = (drive / "scenario.toml").read_text()
    start = float(text.split("start_unix_s = ")[1].split()[0])
    (tmp_path / "later.toml").write_text(
        text.replace(
            f"start_unix_s = {text.split('start_unix_s = ')[1].split()[0]}", f"start_unix_s = {start + 7200.0}"
        )
    )
    subprocess.run(
        [sys.executable, "-m", "sumhe", "simulate", "--settings", str(tmp_path / "later.toml"), "--out", str(later)],
        check=True,
        env=ENV,
        capture_output=True,
    )
    for name in ("drive.log", "drive.nmea"):
        (tmp_path / name).write_text((drive / name).read_text() + (later / name).read_text())
    both = replay(drive, tmp_path / "drive.log", tmp_path / "drive.nmea")
    first, second = (
        replay(drive, drive / "drive.log", drive / "drive.nmea"),
        replay(later, later / "drive.log", later / "drive.nmea"),
    )
    assert both.returncode == 0, both.stderr
    t = [json.loads(x)["t"] for x in both.stdout.splitlines()]
    t_first = [json.loads(x)["t"] for x in first.stdout.splitlines()]
    t_second = [json.loads(x)["t"] for x in second.stdout.splitlines()]
    assert t[: len(t_first)] == t_first  # the part before the pause as alone
    assert t_second[0] - 1.0 <= t[len(t_first)] and t[-1] == t_second[-1]  # after it: on its own times
    assert abs(len(t) - len(t_first) - len(t_second)) <= 20
    assert "pauses kept 1" in both.stderr and "re-based 0 times" in both.stderr


def fix_at(rx: float, utc: float) -> GnssFix:
    when = dt.datetime.fromtimestamp(utc, dt.timezone.utc)
    return GnssFix(t=rx, time_utc=when, lat_deg=48.0, lon_deg=11.0, alt_m=None, quality=1, valid=True)


def test_nmea_receive_times_are_re_based_only_when_the_loggers_clock_jumped():
    t0 = 1780300800.0
    steps = [(t0, t0), (t0 + 3600.1, t0 + 0.1), (t0 + 3600.2, t0 + 0.2)]  # the logger's clock jumped
    steps += [(t0 + 7200.2, t0 + 3600.2)]  # then a pause of an hour: both clocks moved
    steps += [(t0 + 7200.3, t0 + 7200.3)]  # then the receiver's UTC jumped on its own
    counters = NmeaCounters()
    out = [f.t for f in rebase_receive_times([fix_at(rx, utc) for rx, utc in steps], "x.nmea", counters)]
    assert out == pytest.approx([t0, t0 + 0.1, t0 + 0.2, t0 + 3600.2, t0 + 3600.3], abs=1e-6)
    assert counters.rebases == 1


def test_a_replay_without_one_valid_nmea_sentence_exits_1_with_the_reason(drive, tmp_path):
    bad = tmp_path / "bad.nmea"
    bad.write_bytes(b"(1780300800.1) $GPGGA,garbage*00\n(1780300800.2) \x1b[31mhello\n")
    result = replay(drive, drive / "drive.log", bad)
    assert result.returncode == 1 and result.stdout == ""
    assert f"error: nothing to estimate from: {bad}: no valid fix in the NMEA log" in result.stderr
    assert "checksum_errors=1 garbled=1" in result.stderr


def test_a_receiver_on_a_serial_port_sending_implausible_values_loses_no_epoch():
    """Through the serial source on a real pty: 1e9 kn, altitude and HDOP 1e308, a ZDA year 2099 in between."""
    from test_serial_source import Pty, run, settings, until

    from sumhe.io.serial import SerialNmeaSource

    pty = Pty()
    epochs = [
        [gga("120000"), rmc("120000")],
        [gga("120001", alt="1e308", hdop="1e308"), rmc("120001", knots="1e9")],
        [zda("120002", 2099), gga("120002")],
        [gga("120003"), rmc("120003")],
        [gga("120004"), rmc("120004")],
    ]

    async def main():
        async with SerialNmeaSource(settings(pty.path)) as source:
            await until(lambda: source.stats.connected)
            fixes = []
            for lines in epochs:
                pty.write("".join(f"{x}\r\n" for x in lines).encode())
                fixes.append(await anext(source))
            return fixes, source.decoder.counters

    try:
        fixes, counters = run(main())
    finally:
        pty.close()
    assert [f.time_utc.isoformat()[:19] for f in fixes] == [f"2024-05-17T12:00:0{s}" for s in range(5)]
    assert all(f.valid for f in fixes)
    assert (fixes[1].alt_m, fixes[1].hdop, fixes[1].speed_mps) == (None, None, None)
    assert fixes[0].alt_m == 545.4 and counters.implausible == 4 and counters.backwards == 0

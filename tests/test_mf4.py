"""MF4 logs (python-can's MF4 reader on asammdf) and drives of several log files read as one."""

from __future__ import annotations

import gc
import math
import random
import statistics
import subprocess
import sys
from pathlib import Path

import can
import pytest

from sumhe.config import load_config
from sumhe.errors import SourceError
from sumhe.io.can import LogStats, first_timestamp, read_log, read_logs
from sumhe.io.replay import RecordedDrive
from sumhe.messages import CanSample, GnssFix

from canframes import MESSAGE_FIELDS
from loggerframes import T0, drive_frames, frame, write_log

REPO = Path(__file__).resolve().parents[1]
REAL_DRIVE = REPO.parent / "shared" / "data" / "real_drives" / "canedge_obd_2021-07-26_a"
REAL_LOGS = sorted(REAL_DRIVE.glob("*.MF4")) if REAL_DRIVE.is_dir() else []


def frames_of(t0: float, n: int, dt: float, channel: int, arbitration_id: int = 0x100) -> list[can.Message]:
    return [frame(t0 + i * dt, arbitration_id, bytes([i % 256, channel, 0, 0]), channel) for i in range(n)]


def test_mf4_round_trip_keeps_times_ids_payloads_and_channels(tmp_path):
    sent = drive_frames(3.0)
    got = list(read_log(write_log(tmp_path / "drive.MF4", sent)))  # the suffix in any case
    assert len(got) == len(sent)
    assert [m.timestamp for m in got] == pytest.approx([m.timestamp for m in sent], abs=1e-6)
    assert [(m.arbitration_id, bytes(m.data), m.channel) for m in got] == [
        (m.arbitration_id, bytes(m.data), m.channel) for m in sent
    ]


def test_consecutive_files_in_any_order_are_one_drive_in_time_order(tmp_path):
    parts = [frames_of(T0 + 10.0 * k, 100, 0.1, channel=1 + k % 2) for k in range(3)]
    paths = [write_log(tmp_path / f"part{k}.mf4", part) for k, part in enumerate(parts)]
    shuffled = paths[:]
    random.Random(4).shuffle(shuffled)
    stats = LogStats()
    frames = read_logs([paths[2], paths[0], paths[1]], stats)
    assert stats.first_t == pytest.approx(T0)  # known before the first frame is read
    first = next(frames)
    assert stats.files == 1  # the later files are opened when the stream reaches them
    rest = list(frames)
    t = [first.timestamp] + [m.timestamp for m in rest]
    assert len(t) == 300 and t == sorted(t)
    assert (stats.files, stats.frames) == (3, 300)
    assert [m.timestamp for m in read_logs(shuffled)] == t


def test_files_of_parallel_buses_are_merged_by_time(tmp_path):
    bus1 = write_log(tmp_path / "can1.mf4", frames_of(T0, 50, 0.02, channel=1))
    bus2 = write_log(tmp_path / "can2.log", frames_of(T0 + 0.01, 50, 0.02, channel=2, arbitration_id=0x200))
    got = list(read_logs([bus2, bus1]))
    assert [m.timestamp for m in got] == sorted(m.timestamp for m in got)
    assert [m.arbitration_id for m in got[:4]] == [0x100, 0x200, 0x100, 0x200]


def test_a_log_without_frames_is_left_out(tmp_path):
    empty = write_log(tmp_path / "empty.mf4", [])
    full = write_log(tmp_path / "full.mf4", frames_of(T0, 5, 0.1, channel=1))
    assert first_timestamp(empty) is None
    stats = LogStats()
    assert len(list(read_logs([empty, full], stats))) == 5 and stats.files == 1


@pytest.mark.filterwarnings("ignore::pytest.PytestUnraisableExceptionWarning")  # asammdf's __del__ after a failed open
def test_bad_mf4_files_are_source_errors_naming_the_file(tmp_path):
    good = write_log(tmp_path / "good.mf4", frames_of(T0, 200, 0.01, channel=1))
    truncated = tmp_path / "truncated.mf4"
    truncated.write_bytes(good.read_bytes()[: good.stat().st_size // 2])
    text = tmp_path / "notes.mf4"
    text.write_text("not an MDF file\n" * 10)
    for path, what in [
        (truncated, "cannot read CAN log"),
        (text, "cannot read CAN log"),
        (tmp_path / "x.mf4", "not found"),
    ]:
        with pytest.raises(SourceError, match=what) as err:
            read_logs([good, path])
        assert path.name in str(err.value)
    gc.collect()  # asammdf's half-built readers complain in __del__: here, under the filter above


def test_mf4_without_asammdf_names_the_extra(tmp_path):
    """Where asammdf is not installed (simulated by blocking its import in a fresh interpreter)."""
    log = write_log(tmp_path / "drive.mf4", frames_of(T0, 5, 0.1, channel=1))
    code = "import sys; sys.modules['asammdf'] = None; from sumhe.cli import main; sys.exit(main(sys.argv[1:]))"
    done = subprocess.run(
        [sys.executable, "-c", code, "candump", str(log)], capture_output=True, text=True, timeout=120, check=False
    )
    assert done.returncode == 1
    assert "needs the asammdf package: pip install 'sumhe[mf4]'" in done.stderr
    assert str(log) in done.stderr


@pytest.mark.skipif(not REAL_LOGS, reason=f"the real CANedge drive is not in {REAL_DRIVE}")
def test_real_canedge_drive_first_file():
    """The first of the real drive's five MF4 files, read and decoded with configs/canedge-obd.toml."""
    first = REAL_LOGS[0]
    stats = LogStats()
    channels: dict[object, int] = {}
    for msg in read_logs([first], stats):
        channels[msg.channel] = channels.get(msg.channel, 0) + 1
    assert stats.frames == 65296 and stats.first_t == pytest.approx(1627274455.0125)
    assert set(channels) == {1, 2}
    drive = RecordedDrive(load_config(REPO / "configs" / "canedge-obd.toml", env={}), [first])
    samples = list(drive.samples())
    assert [s.t for s in samples] == sorted(s.t for s in samples)
    speed = [s.value for s in samples if isinstance(s, CanSample) and s.quantity == "speed"]
    yaw = [s.value for s in samples if isinstance(s, CanSample) and s.quantity == "yaw_rate"]
    fixes = [s for s in samples if isinstance(s, GnssFix)]
    span = samples[-1].t - samples[0].t
    assert len(speed) / span == pytest.approx(2.0, rel=0.05)  # OBD PID 0x0D polled at 2 Hz
    assert max(speed) * 3.6 == pytest.approx(round(max(speed) * 3.6))  # whole km/h
    assert len(yaw) / span == pytest.approx(100.0, rel=0.05)
    assert len(fixes) == 510 and drive.decoder is not None and drive.decoder.gnss is not None
    assert drive.decoder.gnss.stats.incomplete == 0
    valid = [f for f in fixes if f.valid]
    assert valid and all(f.t - fixes[0].t > 100.0 for f in valid)  # no valid fix for the first ~110 s
    assert all(55.0 < f.lat_deg < 57.0 and 9.0 < f.lon_deg < 11.0 for f in valid)  # near Aarhus
    assert drive.decoder.stats.decode_errors == 0 and not drive.decoder.silent()


@pytest.mark.parametrize("source", ["written", "real"])
def test_bulk_mf4_reader_gives_python_cans_frames(tmp_path, source):
    """sumhe reads MF4 a chunk at a time (sumhe.io.mf4): the same frames as python-can's reader, field by field."""
    from sumhe.io.mf4 import CHUNK_RECORDS, BulkMF4Reader

    if source == "real":
        if not REAL_LOGS:
            pytest.skip(f"the shared real drive is not at {REAL_DRIVE}")
        path = REAL_LOGS[-1]
    else:  # more than one chunk, extended and standard ids, two channels, payloads of 0-8 bytes
        sent = [
            frame(T0 + i * 1e-3, 0x18FEF100 + i % 3 if i % 5 == 0 else 0x100 + i % 7, bytes(range(i % 9)), 1 + i % 2)
            for i in range(CHUNK_RECORDS + 1234)
        ]
        for k, msg in enumerate(sent):
            msg.is_extended_id = k % 5 == 0
        path = write_log(tmp_path / "drive.mf4", sent)

    def fields(reader):
        with reader:
            return [tuple(getattr(m, f) for f in MESSAGE_FIELDS) for m in reader]

    ours, theirs = fields(BulkMF4Reader(path)), fields(can.LogReader(path))
    assert len(ours) > 1000 and ours == theirs


@pytest.mark.skipif(not REAL_LOGS, reason=f"the real CANedge drive is not in {REAL_DRIVE}")
def test_real_canedge_module_rates_its_headings_poor_until_it_settles(tmp_path):
    """Its heading accuracy mapped (``gps.signals.heading_accuracy``), the real drive's first file: the module rates its
    first headings at degrees, those of its settled minutes near half a degree."""
    text = (REPO / "configs" / "canedge-obd.toml").read_text()
    mapping = 'heading_accuracy = { signal = "gnss_attitude.HeadingAccuracy", valid = "AttitudeValid", channel = 2 }\n'
    config = tmp_path / "rated.toml"
    config.write_text(text.replace("\n[gps.signals]", f"\n[gps.signals]\n{mapping}", 1))  # its comment moves down
    drive = RecordedDrive(load_config(config, env={}), REAL_LOGS[:1])
    rated = [f for f in drive.samples() if isinstance(f, GnssFix) and f.heading_rad is not None]
    sigmas = [math.degrees(f.heading_sigma_rad) for f in rated if f.heading_sigma_rad is not None]
    assert len(sigmas) == len(rated) > 300
    assert max(sigmas[:60]) > 20.0 and 0.3 < statistics.median(sigmas[-200:]) < 1.5

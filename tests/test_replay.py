import asyncio
import time
from pathlib import Path

import can
import pytest

from sumhe.config import load_config
from sumhe.io.nmea_format import format_gga, format_rmc
from sumhe.io.replay import PacedReplay, log_samples, merge_by_time
from sumhe.messages import CanSample, GnssFix

from canframes import speed_frame, yaw_frame

REPO_CONFIG = Path(__file__).resolve().parents[1] / "configs" / "default.toml"


def _write_can_log(path, t0: float, seconds: float) -> None:
    frames = []
    for i in range(int(seconds * 50)):
        t = t0 + i * 0.02
        frames.append(speed_frame(t, 36.0, i))
        frames.append(yaw_frame(t + 0.001, 5.0, i))
    with can.CanutilsLogWriter(str(path)) as w:
        for f in frames:
            w.on_message_received(f)


def _nmea_lines(t0: float, seconds: float, prefix: bool = True) -> list[str]:
    lines = []
    for i in range(int(seconds * 10)):
        t = t0 + 0.1 * i
        gga = format_gga(t, 48.1 + i * 1e-6, 11.5, 1, sats=10, hdop=0.8, alt_msl_m=520.0)
        rmc = format_rmc(t, 48.1 + i * 1e-6, 11.5, speed_mps=10.0, course_rad=0.0)
        for s in (gga, rmc):
            lines.append(f"({t + 0.05:.6f}) {s}" if prefix else s)
    return lines


def test_merge_by_time_orders_and_keeps_ties_stable():
    a = [CanSample(1.0, "speed", 1.0), CanSample(3.0, "speed", 3.0)]
    b = [CanSample(1.0, "yaw_rate", 0.0), CanSample(2.0, "yaw_rate", 0.0)]
    out = list(merge_by_time(a, b))
    assert [(s.t, s.quantity) for s in out] == [(1.0, "speed"), (1.0, "yaw_rate"), (2.0, "yaw_rate"), (3.0, "speed")]


def test_log_samples_merges_can_and_nmea_in_time_order(tmp_path):
    t0 = 1780300800.0
    _write_can_log(tmp_path / "drive.log", t0, 2.0)
    (tmp_path / "drive.nmea").write_text("\n".join(_nmea_lines(t0, 2.0)) + "\n")
    cfg = load_config(REPO_CONFIG, env={})
    samples = list(log_samples(cfg, tmp_path / "drive.log", tmp_path / "drive.nmea"))
    ts = [s.t for s in samples]
    assert ts == sorted(ts)
    fixes = [s for s in samples if isinstance(s, GnssFix)]
    speeds = [s for s in samples if isinstance(s, CanSample) and s.quantity == "speed"]
    yaws = [s for s in samples if isinstance(s, CanSample) and s.quantity == "yaw_rate"]
    assert len(fixes) == 20 and all(f.valid for f in fixes)
    assert len(speeds) == 100 and speeds[0].value == pytest.approx(10.0)
    assert len(yaws) == 100 and yaws[0].value == pytest.approx(0.0872665, rel=1e-4)


def test_clock_offset_moves_fixes_only(tmp_path):
    t0 = 1780300800.0
    _write_can_log(tmp_path / "drive.log", t0, 1.0)
    (tmp_path / "drive.nmea").write_text("\n".join(_nmea_lines(t0, 1.0)) + "\n")
    cfg = load_config(REPO_CONFIG, env={})
    base = list(log_samples(cfg, tmp_path / "drive.log", tmp_path / "drive.nmea"))
    moved = list(log_samples(cfg, tmp_path / "drive.log", tmp_path / "drive.nmea", offset_s=-0.5))
    fix_t = [s.t for s in base if isinstance(s, GnssFix)]
    moved_t = [s.t for s in moved if isinstance(s, GnssFix)]
    assert moved_t == pytest.approx([t - 0.5 for t in fix_t])
    assert [s.t for s in moved if isinstance(s, CanSample)] == [s.t for s in base if isinstance(s, CanSample)]
    assert [s.t for s in moved] == sorted(s.t for s in moved)


def test_paced_replay_keeps_real_time_factor():
    samples = [CanSample(100.0 + 0.1 * i, "speed", 0.0) for i in range(6)]

    async def run(speed: float) -> float:
        start = time.monotonic()
        got = [s async for s in PacedReplay(samples, speed=speed)]
        assert got == samples
        return time.monotonic() - start

    assert asyncio.run(run(5.0)) >= 0.5 / 5.0 * 0.9  # 0.5 s of data at 5x
    assert asyncio.run(run(0.0)) < 0.5  # as fast as possible


def test_replay_of_missing_file_is_a_clear_error(tmp_path):
    cfg = load_config(REPO_CONFIG, env={})
    from sumhe.errors import SourceError

    with pytest.raises(SourceError):
        list(log_samples(cfg, None, tmp_path / "nope.nmea"))

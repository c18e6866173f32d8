"""A long drive chained from simulated segments, replayed and fed to the daemon's service with memory read as it
goes (the figures are the benchmark's; here only that it works and what it reports)."""

from __future__ import annotations

import asyncio
import itertools
import math

import numpy as np
import pytest

from sumhe.bench.soak import GAP_S, chained_drive, soak_daemon, soak_replay
from sumhe.errors import ConfigError
from sumhe.io.can import LogStats, read_logs
from sumhe.io.nmea import iter_fixes
from sumhe.sim import load_settings, load_truth

SEGMENT_S = 40.0


@pytest.fixture(scope="module")
def chained(tmp_path_factory):
    root = tmp_path_factory.mktemp("soak")
    return root, chained_drive(root, 3, seed=2, segment_s=SEGMENT_S)


def test_segments_continue_each_other_in_time_and_place(chained):
    root, (can_logs, nmea_logs) = chained
    assert [p.parent.name for p in can_logs] == ["hour00", "hour01", "hour02"]
    for before, after in itertools.pairwise(can_logs):
        end, start = load_truth(before.parent / "truth.csv"), load_truth(after.parent / "truth.csv")
        assert start.t[0] == pytest.approx(end.t[-1] + GAP_S, abs=0.2)
        metres = np.hypot((start.lat[0] - end.lat[-1]) * 111_320, (start.lon[0] - end.lon[-1]) * 71_500)
        assert metres < 2.0
    frames = [m.timestamp for m in read_logs(can_logs, LogStats())]
    assert np.all(np.diff(frames) >= 0) and frames[-1] - frames[0] == pytest.approx(3 * SEGMENT_S + 2 * GAP_S, abs=1.0)
    fixes = [f.t for p in nmea_logs for f in iter_fixes(p)]
    assert np.all(np.diff(fixes) > 0)
    stamps = [p.stat().st_mtime_ns for p in can_logs]
    again = chained_drive(root, 3, seed=2, segment_s=SEGMENT_S)  # reused, not simulated again
    assert again == (can_logs, nmea_logs) and [p.stat().st_mtime_ns for p in can_logs] == stamps
    assert load_settings(can_logs[1].parent / "scenario.toml").seed == 3


def test_soak_replay_reads_memory_every_segment(chained):
    _, (can_logs, nmea_logs) = chained
    lines = []
    result = soak_replay(can_logs, nmea_logs, "ekf", lines.append, every_s=60.0)  # progress comes every 60 s
    assert result.summary.span_s == pytest.approx(3 * SEGMENT_S + 2 * GAP_S, abs=1.0)
    assert result.summary.estimates > 1000 and result.summary.input["files"] == 3
    assert [round(p.data_s / 60.0) for p in result.points] == [0, 1, 2, 2]  # the last: the end
    assert all(p.rss_mb > 10 and p.peak_mb >= 10 for p in result.points)
    assert math.isfinite(result.growth_after_first_hour) and len(lines) == len(result.points) - 1


def test_soak_daemon_sends_every_estimate_to_its_client(chained):
    _, (can_logs, nmea_logs) = chained
    status, points, received = asyncio.run(soak_daemon(can_logs[:1], nmea_logs[:1], "ekf", 8.0, every_s=SEGMENT_S / 4))
    # an estimator that falls behind on a busy machine skips epochs, and the client shares the daemon's event loop:
    # a burst after a slow solve may overflow its socket buffer
    assert status["estimates"] > 100 and 0.9 * status["estimates"] <= status["sent"] <= status["estimates"]
    assert 0.9 * status["sent"] <= received <= status["sent"]
    assert status["time"]["stale"] == 0 and status["time"]["future"] == 0
    assert points[-1].data_s == pytest.approx(SEGMENT_S, abs=3.0) and len(points) >= 4
    # the collector policy (sumhe.service.collector): the start-up objects frozen (~110 000 without it), and what is
    # made later still collected (the objects tracked do not grow with the data)
    assert all(p.tracked < 30_000 for p in points[:-1]) and points[-2].tracked < points[0].tracked + 5_000
    assert status["gc"]["gen0"]["count"] > 0 and status["gc"]["frozen"] == 0  # unfrozen when it stopped


def test_soak_daemon_refuses_a_bad_run_without_leaving_its_socket_open(chained, tmp_path):
    _, (can_logs, nmea_logs) = chained
    with pytest.raises(ConfigError, match="no-such"):
        asyncio.run(soak_daemon(can_logs[:1], nmea_logs[:1], "no-such", 8.0))
    empty = tmp_path / "empty.log"
    empty.write_text("")
    with pytest.raises(ValueError, match="no usable sample"):
        asyncio.run(soak_daemon([empty], [empty], "ekf", 8.0))

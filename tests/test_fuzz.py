"""Fuzzing the NMEA and candump decoders with a small budget (issue 15, item 6): no exception, every fix valid and
in range or not valid, every CAN line a frame or counted malformed, every frame counted in one class
(:mod:`sumhe.bench.fuzz`; ``sumhe bench fuzz`` runs 10^6 lines)."""

from __future__ import annotations

import random
import tempfile
from pathlib import Path

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from sumhe.bench.fuzz import (
    FuzzReport,
    candump_line,
    fuzz_candump,
    fuzz_nmea,
    generate,
    nmea_line,
    nmea_problems,
)
from sumhe.cli import main
from sumhe.io.can import LogStats, read_log
from sumhe.io.nmea import NmeaCounters
from sumhe.messages import GnssFix

BUDGET = settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.too_slow])
SEEDS = st.integers(0, 2**32 - 1).map(random.Random)
"""The lines' random source, drawn as a seed: a ``st.randoms()`` draws its numbers from hypothesis's own buffer, and
300 generated lines overran it now and then (``FailedHealthCheck: data_too_large``, a flaky failure)."""


@BUDGET
@given(SEEDS, st.integers(1, 300))
def test_fuzzed_nmea_lines_never_crash_and_every_fix_is_in_range(rng, n):
    report = FuzzReport()
    fuzz_nmea(generate(rng, n, nmea_line), report)
    assert report.crashes == 0, report.first_crashes
    assert report.problems == []
    assert report.nmea_lines == n


@BUDGET
@given(SEEDS, st.integers(1, 300))
def test_fuzzed_candump_lines_never_crash_and_every_line_is_accounted_for(rng, n):
    report = FuzzReport()
    with tempfile.TemporaryDirectory() as tmp:
        fuzz_candump(generate(rng, n, candump_line), report, Path(tmp))
    assert report.crashes == 0, report.first_crashes
    assert report.problems == []


def test_the_checks_find_what_they_look_for():
    """The fuzz checks can fail: a fix with an implausible speed, a valid fix without a position, counters that do
    not add up."""
    bad = GnssFix(t=1.0, time_utc=None, lat_deg=None, lon_deg=None, alt_m=None, quality=1, valid=True, speed_mps=1e9)
    problems = nmea_problems([bad], NmeaCounters(fragments=2, sentences=1, fixes=1))
    assert len(problems) == 3


def test_an_fd_flags_digit_above_9_is_a_malformed_line_not_the_end_of_the_log(tmp_path):
    """python-can reads ``##A`` as a decimal digit and raised, which ended the whole file (found by the fuzzer)."""
    log = tmp_path / "drive.log"
    log.write_text("(1.0) can0 1A0##A0011\n(2.0) can0 1A0#0011\n")
    stats = LogStats()
    frames = list(read_log(log, stats))
    assert [m.timestamp for m in frames] == [2.0] and stats.malformed == 1 and stats.error == ""


def test_bench_fuzz_prints_lines_per_second_and_no_crash(capsys):
    assert main(["bench", "fuzz", "--lines", "3000", "--seed", "7"]) == 0
    out = capsys.readouterr().out
    assert "fuzz: 3000 lines (seed 7)" in out and "lines/s; 0 crashes, 0 problems" in out


@pytest.mark.parametrize("seed", [0, 1])
def test_the_generator_reaches_the_decoders_deep_parts(seed):
    """Not just garbage: fixes come out, values are found implausible, frames decode, FD and over-long frames are
    refused."""
    rng = random.Random(seed)
    report = FuzzReport()
    fuzz_nmea(generate(rng, 3000, nmea_line), report)
    with tempfile.TemporaryDirectory() as tmp:
        fuzz_candump(generate(rng, 3000, candump_line), report, Path(tmp))
    assert report.valid_fixes > 100 and report.nmea_counters.implausible > 10
    s = report.can_stats
    assert report.samples > 100 and s.fd_frames > 10 and s.long_frames > 10 and s.crc_errors > 10

"""One recorded drive through one estimator, in bounded memory: what ``sumhe replay`` prints and ``sumhe fleet``
tabulates.

:func:`replay_drive` runs the samples of a :class:`~sumhe.io.replay.RecordedDrive` through the
:class:`~sumhe.service.pipeline.Pipeline`, with the fixes of outage windows cut out (:mod:`sumhe.bench.outages`),
writes each estimate as the JSON line the UDP output sends, and returns a :class:`DriveSummary`. Everything it
keeps grows with nothing but the outage windows: solve times and errors go into fixed histograms
(:func:`~sumhe.service.histogram.latency_histogram`), modes into a counter, positions only near the windows; a day of
data costs what an hour does.

Units: seconds (``t`` on the drive's clock), metres, milliseconds where named ``_ms``.
"""

from __future__ import annotations

import contextlib
import dataclasses
import gc
import json
import math
import time
from collections import Counter
from collections.abc import Callable, Iterator, Mapping, Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, TextIO

import numpy as np

from sumhe.bench.metrics import throughput
from sumhe.bench.outages import (
    MAX_INTERPOLATION_GAP_S,
    FixCut,
    ModeShares,
    OutageErrors,
    mode_shares,
    outage_errors,
    outage_windows,
)
from sumhe.errors import ConfigError
from sumhe.estimator.base import Estimator
from sumhe.geo import LocalFrame
from sumhe.io.replay import RecordedDrive, chunks
from sumhe.io.udp import json_line
from sumhe.messages import Estimate
from sumhe.service.collector import young_collections_every
from sumhe.service.histogram import Histogram
from sumhe.service.pipeline import MonotonicOutput, Pipeline

if TYPE_CHECKING:  # the simulator (and python-can with it) is not loaded to replay a drive
    from sumhe.sim.truth import Truth

TRUTH_CHUNK = 4096
"""Estimates compared with the truth at once (vectorised), then forgotten."""

PROGRESS_EVERY_S = 60.0
"""How often (s of data) :func:`replay_drive` reports progress."""
READ_AHEAD = 4096
"""Samples read from the logs at a time before they are fed to the estimator: reading and estimating in turn,
sample by sample, made the replay of the bundled drive a sixth slower (each half of the loop evicting the other's
code and data from the CPU caches); a few MB at most."""

GAUGES = frozenset({"window", "period_s"})
"""Estimator statistics that are levels, not counters: :func:`counter_deltas` reports them as they are."""


@dataclass(frozen=True, slots=True)
class TruthErrors:
    """Horizontal errors (m) of every estimate against the truth at its time: count, mean, 95th percentile (from
    the histogram) and maximum."""

    scored: int
    mean_m: float
    p95_m: float
    max_m: float


class _TruthScore:
    """Estimates against a :class:`~sumhe.sim.truth.Truth` (its lat/lon of antenna 1), :data:`TRUTH_CHUNK` at a
    time; only the error histogram is kept."""

    def __init__(self, truth: Truth) -> None:
        self.truth = truth
        self.frame = LocalFrame(float(truth.lat[0]), float(truth.lon[0]), 0.0)
        self.errors = Histogram()
        self._t: list[float] = []
        self._lat: list[float] = []
        self._lon: list[float] = []

    def add(self, est: Estimate) -> None:
        self._t.append(est.t)
        self._lat.append(est.lat_deg)
        self._lon.append(est.lon_deg)
        if len(self._t) >= TRUTH_CHUNK:
            self.flush()

    def flush(self) -> None:
        if not self._t:
            return
        t = np.asarray(self._t)
        at = self.truth.at(t)
        est = self.frame.to_enu(np.asarray(self._lat), np.asarray(self._lon))
        ref = self.frame.to_enu(at.lat, at.lon)
        inside = (t >= self.truth.t[0]) & (t <= self.truth.t[-1])
        self.errors.extend(np.hypot(est[:, 0] - ref[:, 0], est[:, 1] - ref[:, 1])[inside])
        self._t, self._lat, self._lon = [], [], []

    def result(self) -> TruthErrors:
        self.flush()
        e = self.errors
        return TruthErrors(e.n, e.mean, e.percentile(95.0), e.max)


class Recorder:
    """Writes estimates as JSON lines (to ``out``, or nowhere; in time order: one stamped before the last written
    is left out, counted ``out_of_order``, one stamped ahead of the input is written in its place,
    :class:`~sumhe.service.pipeline.MonotonicOutput`) and keeps what the
    summary needs in bounded memory:
    solve times (ms, histogram), the count of each mode, the distance travelled (m, between consecutive
    estimates), the positions of the estimates near the outage ``windows`` (absolute, s) and, with a truth, the
    error histogram against it."""

    def __init__(self, windows: Sequence[tuple[float, float]], out: TextIO | None, truth: Truth | None) -> None:
        self.windows = windows
        self.out = out
        self.solve_ms = Histogram()
        self.modes: Counter[str] = Counter()
        self.distance_m = 0.0
        self.t: list[float] = []
        self.lat: list[float] = []
        self.lon: list[float] = []
        self._truth = _TruthScore(truth) if truth is not None else None
        self._last: tuple[float, float] | None = None
        self.order = MonotonicOutput()
        self._unwritten: list[Estimate] = []
        """Estimates let through but not yet written: written :data:`READ_AHEAD` at a time, as samples are read."""

    def write(self, estimates: list[Estimate], now: float) -> None:
        """Take the estimates made when the input's clock was at ``now`` (s; ``inf`` at the end)."""
        margin = MAX_INTERPOLATION_GAP_S
        for est in estimates:
            if est.solve_ms > 0:
                self.solve_ms.add(est.solve_ms)
            self.modes[est.mode] += 1
            if self._last is not None:
                self.distance_m += math.hypot(est.east_m - self._last[0], est.north_m - self._last[1])
            self._last = (est.east_m, est.north_m)
            if self.windows and any(start - margin <= est.t <= end + margin for start, end in self.windows):
                self.t.append(est.t)
                self.lat.append(est.lat_deg)
                self.lon.append(est.lon_deg)
            if self._truth is not None:
                self._truth.add(est)
        if self.out is None:
            return
        self._unwritten += self.order.release(estimates, now)
        if math.isinf(now):
            self._unwritten += self.order.flush()
        if len(self._unwritten) >= READ_AHEAD or math.isinf(now):
            self.flush()

    def flush(self) -> None:
        """Write the estimates let through so far (at the end, and where the replay is interrupted)."""
        if self.out is not None and self._unwritten:
            self.out.write("\n".join([json_line(est) for est in self._unwritten]) + "\n")
            self._unwritten = []

    def truth_errors(self) -> TruthErrors | None:
        return self._truth.result() if self._truth is not None else None


@dataclass(frozen=True)
class DriveSummary:
    """What one replay of one drive gave (see the module docstring). ``span_s`` is the time from the first to the
    last sample, ``wall_s``/``cpu_s`` the computing time of the loop (the estimator built before it),
    ``estimator_stats`` the estimator's statistics over this drive (:func:`counter_deltas`), ``input`` the
    counters of the logs and decoders, ``warnings`` mapped quantities that gave nothing."""

    estimator: str
    fixes: int
    valid_fixes: int
    fixes_removed: int
    can_samples: int
    estimates: int
    dropped: Mapping[str, int]
    span_s: float
    wall_s: float
    cpu_s: float
    distance_m: float
    solve_p50_ms: float
    solve_p99_ms: float
    modes: ModeShares
    estimator_stats: Mapping[str, float | int | str]
    outages: Sequence[OutageErrors]
    outages_all: OutageErrors | None
    truth: TruthErrors | None
    input: Mapping[str, Any]
    warnings: Sequence[str]
    first_t: float

    @property
    def speed(self) -> float:
        """Times faster than real time (seconds of data per second of wall time)."""
        return throughput(self.span_s, self.wall_s)

    @property
    def fixes_used(self) -> int:
        """The fixes the estimator took (its ``gps_ok`` counter where it keeps one, else the valid fixes fed)."""
        used = self.estimator_stats.get("gps_ok")
        return int(used) if isinstance(used, int) else self.valid_fixes

    def to_json(self) -> dict[str, Any]:
        """Plain data (NaN as None) for a JSON record."""
        return _plain({**dataclasses.asdict(self), "speed": self.speed, "fixes_used": self.fixes_used})

    def lines(self) -> list[str]:
        """The summary ``sumhe replay`` prints."""
        d = self.dropped
        out = [
            f"replay: {self.estimator}: {self.fixes} fixes ({self.valid_fixes} valid), {self.can_samples} CAN "
            f"samples, {self.estimates} estimates; dropped late {d['late']}, duplicate {d['duplicate']}, zero "
            f"time {d['zero_time']}, clock resets {d['clock_resets']}, out of order (not written) "
            f"{d['out_of_order']}; solve p50/p99 {self.solve_p50_ms:.2f}/"
            f"{self.solve_p99_ms:.2f} ms; {self.span_s:.0f} s of data in {self.wall_s:.1f} s "
            f"({self.speed:.0f}x real time; CPU {self.cpu_s:.1f} s: {throughput(self.span_s, self.cpu_s):.0f}x)",
            _modes_line(self.modes),
            "estimator: "
            + ", ".join(
                f"{k} {v:.4g}" if isinstance(v, float) else f"{k} {v}" for k, v in self.estimator_stats.items()
            ),
            *_input_lines(self.input),
            *(f"warning: {line}" for line in self.warnings),
        ]
        if self.truth is not None:
            e = self.truth
            out.append(
                f"errors against the truth (m): {e.scored} estimates; mean {e.mean_m:.2f}, p95 {e.p95_m:.2f}, "
                f"max {e.max_m:.2f}"
            )
        if self.outages_all is not None:
            out.append("errors against the removed fixes (m):")
            out += [_errors_line(f"{e.start - self.first_t:g}+{e.end - e.start:g}", e) for e in self.outages]
            out.append(_errors_line("all", self.outages_all))
        return out


def counter_deltas(
    before: Mapping[str, float | int | str], after: Mapping[str, float | int | str]
) -> dict[str, float | int | str]:
    """An estimator's statistics over a stretch of its life: integer counters as the difference ``after - before``
    (an estimator reused across drives keeps counting), everything else (names, :data:`GAUGES`, floats) as
    ``after`` says."""
    out: dict[str, float | int | str] = {}
    for key, value in after.items():
        old = before.get(key, 0)
        counter = isinstance(value, int) and not isinstance(value, bool) and key not in GAUGES
        out[key] = value - old if counter and isinstance(old, int) else value
    return out


def replay_drive(
    drive: RecordedDrive,
    estimator: Estimator,
    outages: Sequence[tuple[float, float]] = (),
    out: TextIO | None = None,
    truth: Truth | None = None,
    progress: Callable[[float], None] | None = None,
) -> DriveSummary:
    """Replay ``drive`` through ``estimator`` (fresh, or :meth:`reset` by the caller), with the fixes of the
    ``outages`` (``(start_s, length_s)``, starts from the drive's first CAN frame) removed; estimates as JSON lines
    to ``out``. ``progress`` is called now and then with the seconds of data done. ConfigError for bad outages."""
    pipeline = Pipeline(drive.config, estimator)
    t0 = drive.first_t
    try:
        cut = FixCut(outage_windows(outages, t0 if math.isfinite(t0) else 0.0))
    except ValueError as e:
        raise ConfigError(f"--outage: {e}") from e
    recorder = Recorder(cut.windows, out, truth)
    stats_before = dict(estimator.stats())
    first_t = last_t = math.nan
    next_report = -math.inf
    wall0, cpu0 = time.perf_counter(), time.process_time()
    push, write = pipeline.push, recorder.write
    keep = cut.keep if cut.windows else None  # no outage: no call a sample to be told so
    with _made_so_far_frozen():
        try:
            for chunk in chunks(drive.samples(), READ_AHEAD):
                for sample in chunk:
                    last_t = sample.t
                    if keep is None or keep(sample):
                        estimates = push(sample)
                        if estimates:
                            write(estimates, last_t)
                    if last_t >= next_report:  # the first sample, then once a minute of data
                        first_t = last_t if math.isnan(first_t) else first_t
                        next_report = last_t + PROGRESS_EVERY_S
                        if progress is not None:
                            progress(last_t - first_t)
            write(pipeline.finish(), math.inf)
        finally:
            recorder.flush()  # an interrupted replay keeps what it estimated, as before the batches
    wall, cpu = time.perf_counter() - wall0, time.process_time() - cpu0
    span = last_t - first_t if math.isfinite(first_t) and math.isfinite(last_t) else 0.0
    stats_after = estimator.stats()
    per_window: Sequence[OutageErrors] = []
    overall = None
    if cut.windows:  # on the estimates' clock: at the fixes' stamped times plus the learned GNSS time offset
        offset = float(stats_after.get("gps_time_offset_s", 0.0))
        per_window, overall = outage_errors(cut.windows, cut.removed, recorder.t, recorder.lat, recorder.lon, offset)
    ts, ps = pipeline.guard.stats, pipeline.stats
    return DriveSummary(
        estimator=estimator.name,
        fixes=ps.fixes,
        valid_fixes=ps.valid_fixes,
        fixes_removed=len(cut.removed),
        can_samples=ps.can_samples,
        estimates=ps.estimates,
        dropped={
            **{k: getattr(ts, k) for k in ("late", "duplicate", "zero_time", "future", "stale", "clock_resets")},
            "out_of_order": recorder.order.out_of_order,
        },
        span_s=span,
        wall_s=wall,
        cpu_s=cpu,
        distance_m=recorder.distance_m,
        solve_p50_ms=recorder.solve_ms.percentile(50.0),
        solve_p99_ms=recorder.solve_ms.percentile(99.0),
        modes=mode_shares(recorder.modes),
        estimator_stats=counter_deltas(stats_before, stats_after),
        outages=per_window,
        outages_all=overall,
        truth=recorder.truth_errors(),
        input=_input_counters(drive),
        warnings=drive.decoder.silent() if drive.decoder is not None else [],
        first_t=t0,
    )


@contextlib.contextmanager
def _made_so_far_frozen() -> Iterator[None]:
    """The objects made before the replay's loop (the imports', the DBCs', the estimator's: 110 000 for the bundled
    drive) kept out of the garbage collector's passes while it runs, and handed back after (nothing stays
    uncollectable): a full pass traversed them all, 66 ms of the bundled drive's loop. The young generation
    collected less often meanwhile (:func:`~sumhe.service.collector.young_collections_every`). Left alone where some
    are frozen already (the caller's to manage)."""
    if gc.get_freeze_count():
        yield
        return
    gc.freeze()
    try:
        with young_collections_every():
            yield
    finally:
        gc.unfreeze()


def _input_counters(drive: RecordedDrive) -> dict[str, Any]:
    """What the logs gave: files and frames, GNSS epochs from CAN."""
    if drive.decoder is None:
        return {}
    ls, ds = drive.log_stats, drive.decoder.stats
    out: dict[str, Any] = {
        "files": ls.files,
        "frames": ds.frames,
        "unused": ds.unused,
        "other_mux": ds.other_mux,
        "invalid": ds.invalid,
        "decode_errors": ds.decode_errors,
        "fd_frames": ds.fd_frames,
        "long_frames": ds.long_frames,
        "malformed": ls.malformed,
        "clock_rebases": ls.rebases,
        "pauses": ls.pauses,
        "ended_early": ls.error,
    }
    if drive.nmea_decoders:
        out["nmea"] = {
            k: sum(getattr(d.counters, k) for d in drive.nmea_decoders)
            for k in ("lines", "fixes", "checksum_errors", "garbled", "implausible", "backwards", "rebases")
        }
    if drive.decoder.gnss is not None:
        gs = drive.decoder.gnss.stats
        out["gnss"] = {
            "fixes": gs.fixes,
            "valid_fixes": gs.valid_fixes,
            "incomplete": gs.incomplete,
            "no_position": gs.no_position,
            "bad_values": gs.bad_values,
        }
    return out


def _input_lines(counters: Mapping[str, Any]) -> list[str]:
    if not counters:
        return []
    c = counters
    out = [
        f"CAN: {c['files']} files, {c['frames']} frames; unused {c['unused']}, other multiplexer values "
        f"{c['other_mux']}, flagged invalid {c['invalid']}, decode errors {c['decode_errors']}, FD frames on classic "
        f"ids {c['fd_frames']}, too long for their message {c['long_frames']}, malformed {c['malformed']}, clock "
        f"re-based {c['clock_rebases']} times, pauses kept {c['pauses']}"
        + (f"; ended early: {c['ended_early']}" if c["ended_early"] else "")
    ]
    if "nmea" in c:
        n = c["nmea"]
        out.append(
            f"NMEA: {n['lines']} lines, {n['fixes']} fixes; checksum errors {n['checksum_errors']}, garbled "
            f"{n['garbled']}, implausible values {n['implausible']}, time going back {n['backwards']}, clock "
            f"re-based {n['rebases']} times"
        )
    if "gnss" in c:
        g = c["gnss"]
        out.append(
            f"GNSS from CAN: {g['fixes']} fixes ({g['valid_fixes']} valid), incomplete epochs {g['incomplete']}, "
            f"epochs without position {g['no_position']}, values out of range {g['bad_values']}"
        )
    return out


def _modes_line(shares: ModeShares) -> str:
    modes = ", ".join(f"{m} {n}" for m, n in sorted(shares.modes.items()))
    return (
        f"modes: {modes or 'none'}; of {shares.epochs} epoch estimates {100 * shares.widened_share:.1f} % on widened "
        f"bounds, {100 * shares.failed_share:.1f} % solver failures (prediction)"
    )


def _errors_line(label: str, e: OutageErrors) -> str:
    return f"  {label}: {e.scored} of {e.fixes} fixes; mean {e.mean_m:.2f}, p95 {e.p95_m:.2f}, max {e.max_m:.2f}"


def _plain(value: Any) -> Any:
    """``value`` as JSON data: NaN and infinities as None, tuples as lists, numpy scalars as Python numbers."""
    text = json.dumps(value, default=lambda v: v.item() if isinstance(v, np.generic) else str(v))
    return json.loads(text, parse_constant=lambda _: None)

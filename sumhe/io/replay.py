"""Replay of recorded drives: CAN logs and NMEA logs merged into one time-ordered stream.

A drive is one or several CAN log files (candump, MF4, ...: consecutive files of one logger, or files of parallel
buses; :func:`~sumhe.io.can.read_logs`) and, with ``gps.source = "nmea"``, one or several NMEA logs; with
``gps.source = "can"`` the fixes come from the CAN frames (:mod:`sumhe.io.can_gnss`). Files the config names (the
DBCs) are looked for beside the logs too. The stream is the same type the live sources produce (an async iterator
of :data:`sumhe.messages.Sample`), so downstream code cannot tell a replay from a car. Pacing is as fast as
possible (``speed=0``), real time (``1``) or any factor, like ``can.MessageSync``; the NMEA clock may be shifted
against the CAN clock by ``offset_s``.
"""

from __future__ import annotations

import asyncio
import dataclasses
import heapq
import itertools
import math
import operator
from collections.abc import AsyncIterator, Collection, Iterable, Iterator, Sequence
from os import PathLike
from pathlib import Path
from typing import TypeVar

import numpy as np

from sumhe.config import Config
from sumhe.errors import ConfigError, SourceError
from sumhe.io.can import LOG_JUMP_S, CanDecoder, LogStats, read_logs
from sumhe.io.fixtime import stamp_fix
from sumhe.io.nmea import NmeaDecoder, iter_fixes, rebase_receive_times
from sumhe.messages import GnssFix, Sample

REORDER_MARGIN_S = 0.1
"""Added to the longest a fix decoded from CAN can come after later-stamped samples (:func:`reorder_hold_s`)."""
FIXES_AHEAD = 64
"""NMEA fixes decoded at a time, ahead of the CAN samples they are merged with: decoding the two logs in turn, a
fix every 15 CAN samples, made reading the bundled drive a seventh slower (each decoder evicting the other's code
and data from the CPU caches, as :data:`sumhe.bench.reprocess.READ_AHEAD` says of reading and estimating)."""

_Item = TypeVar("_Item")


_time = operator.attrgetter("t")


def merge_by_time(*streams: Iterable[Sample]) -> Iterator[Sample]:
    """Merge time-ordered streams into one, ordered by ``t`` (stable: ties keep stream order)."""
    return heapq.merge(*streams, key=_time)


def chunks(items: Iterable[_Item], n: int) -> Iterator[list[_Item]]:
    """``items`` in the same order, in lists of ``n`` (the last shorter): one stage of a pipeline running for a
    while before the next, for the CPU caches' sake. A loop over each list spares the generator's resumption a
    sample :func:`read_ahead` costs (over the bundled drive's 33 603 samples 0.9 -> 0.26 ms)."""
    it = iter(items)
    while chunk := list(itertools.islice(it, n)):
        yield chunk


def read_ahead(items: Iterable[_Item], n: int) -> Iterator[_Item]:
    """``items`` in the same order, taken ``n`` at a time (:func:`chunks`)."""
    for chunk in chunks(items, n):
        yield from chunk


def time_ordered(samples: Iterable[Sample], hold_s: float) -> Iterator[Sample]:
    """``samples`` in time order, given that none comes more than ``hold_s`` (s) after a later-stamped one: each
    is held until a sample ``hold_s`` newer has arrived (stable for equal times)."""
    held: list[tuple[float, int, Sample]] = []
    order = itertools.count()
    newest = -math.inf
    for s in samples:
        heapq.heappush(held, (s.t, next(order), s))
        newest = max(newest, s.t)
        while held[0][0] < newest - hold_s:
            yield heapq.heappop(held)[2]
    while held:
        yield heapq.heappop(held)[2]


def reorder_hold_s(config: Config) -> float:
    """How much later (s) a fix decoded from CAN may come than samples stamped after it: the epoch's span, the
    receiver latency or (``gps.time = "utc"``) the largest clock offset its stamp may move it back by, a margin."""
    gps = config.gps
    back = max(gps.latency_s, gps.max_clock_offset_s if gps.time == "utc" else 0.0)
    return gps.epoch_span_s + back + REORDER_MARGIN_S


def shift_fixes(fixes: Iterable[GnssFix], offset_s: float) -> Iterator[GnssFix]:
    """Move GNSS fixes onto the CAN clock: ``t + offset_s``."""
    if offset_s == 0.0:
        yield from fixes
        return
    for fix in fixes:
        yield dataclasses.replace(fix, t=fix.t + offset_s)


Paths = str | PathLike[str] | Sequence[str | PathLike[str]] | None
"""One log file, several, or none."""


def paths_of(logs: Paths) -> list[Path]:
    """``logs`` as a list of paths."""
    if logs is None:
        return []
    if isinstance(logs, str | PathLike):
        return [Path(logs)]
    return [Path(p) for p in logs]


def beside_logs(config: Config, logs: Iterable[Path]) -> Config:
    """``config`` with the folders of ``logs`` added to :attr:`~sumhe.config.Config.log_dirs` (where files the
    config names, such as a logger's DBC, are looked for too)."""
    dirs = dict.fromkeys(p.resolve().parent for p in logs)
    return dataclasses.replace(config, log_dirs=tuple(dict.fromkeys((*config.log_dirs, *dirs))))


def check_gps_source(config: Config, nmea_logs: Sequence[object] | None) -> None:
    """ConfigError when the NMEA logs given do not fit ``gps.source``."""
    if config.gps.source == "nmea" and not nmea_logs:
        raise ConfigError(
            f"{config.source}: gps.source = 'nmea': give the NMEA logs with --nmea (or set [gps] source = 'can')"
        )
    if config.gps.source == "can" and nmea_logs:
        raise ConfigError(f"{config.source}: gps.source = 'can': the fixes come from the CAN logs; drop --nmea")


class RecordedDrive:
    """One recorded drive, decoded: :meth:`samples` is its time-ordered stream of samples.

    Reading starts here: SourceError at once for a missing or unreadable log (or an MF4 log without asammdf),
    ConfigError for a mapping the DBCs do not hold. ``quantities`` limits the CAN quantities decoded (None: all
    mapped). ``config`` is the given one with the logs' folders added to
    :attr:`~sumhe.config.Config.log_dirs`; ``decoder`` (None without CAN logs) and ``log_stats`` hold the counters
    of the CAN side, ``nmea_decoders`` (one per NMEA log) those of the NMEA side, ``first_t`` the timestamp of the
    drive's first CAN frame (s; NaN without CAN logs).
    """

    def __init__(
        self,
        config: Config,
        can_logs: Paths = None,
        nmea_logs: Paths = None,
        offset_s: float = 0.0,
        quantities: Collection[str] | None = None,
    ) -> None:
        self.can_logs = paths_of(can_logs)
        self.nmea_logs = paths_of(nmea_logs)
        self.config = beside_logs(config, (*self.can_logs, *self.nmea_logs))
        self.offset_s = offset_s
        for p in self.nmea_logs:
            if not p.is_file():
                raise SourceError(f"{p}: NMEA log not found")
        self.nmea_decoders = [NmeaDecoder() for _ in self.nmea_logs]
        self.log_stats = LogStats()
        self._nmea_times: np.ndarray | None = None
        self._frames = read_logs(self.can_logs, self.log_stats, self.can_pause) if self.can_logs else iter(())
        self.decoder = CanDecoder.from_config(self.config, quantities=quantities) if self.can_logs else None

    @property
    def first_t(self) -> float:
        return self.log_stats.first_t

    def samples(self) -> Iterator[Sample]:
        """Every decoded sample of the drive in time order; fixes stamped with their measurement time
        (:func:`~sumhe.io.fixtime.stamp_fix`; NMEA receive times re-based across jumps of the log's clock
        (:func:`~sumhe.io.nmea.rebase_receive_times`) and moved by ``offset_s`` first)."""
        gps = self.config.gps
        streams: list[Iterable[Sample]] = []
        if self.decoder is not None:
            can_samples = self._can_samples(self.decoder)
            streams.append(time_ordered(can_samples, reorder_hold_s(self.config)) if self.decoder.gnss else can_samples)
        if self.nmea_logs:
            fixes = merge_by_time(
                *(
                    rebase_receive_times(iter_fixes(p, d), str(p), d.counters)
                    for p, d in zip(self.nmea_logs, self.nmea_decoders, strict=True)
                )
            )
            stamped = (stamp_fix(fix, gps) for fix in shift_fixes(fixes, self.offset_s))  # type: ignore[arg-type]
            streams.append(read_ahead(stamped, FIXES_AHEAD))
        return merge_by_time(*streams)

    def can_pause(self, before: float, after: float) -> bool:
        """Whether a CAN log's clock stepping from ``before`` to ``after`` (s) is time that passed (kept) rather than
        the logger's clock jumping (re-based, :class:`~sumhe.io.can.LogClock`): with NMEA logs, a pause where their
        (re-based) receive times reach ``after`` too (the receiver ran on, or both logs resumed there), a jump where
        they do not (they went on near ``before``: only the CAN log's clock jumped); without, always a pause (the
        fixes come in the same CAN logs, on the same clock). The NMEA logs are read for it at the first such step."""
        if not self.nmea_logs:
            return True
        if self._nmea_times is None:
            times = [
                f.t
                for p in self.nmea_logs
                for f in rebase_receive_times(iter_fixes(p, NmeaDecoder()), str(p), NmeaDecoder().counters)
            ]
            self._nmea_times = np.sort(np.array(times, dtype=float))
        t = self._nmea_times
        i = int(np.searchsorted(t, after - LOG_JUMP_S))
        return i < len(t) and t[i] <= after + LOG_JUMP_S

    def unusable(self, valid_fixes: int, can_samples: int) -> str | None:
        """Why a replay of this drive that gave ``valid_fixes`` valid fixes and ``can_samples`` CAN samples had
        nothing to estimate from (the logs, their counters and what to check), or None when it had both."""
        if valid_fixes and can_samples:
            return None
        if not valid_fixes and self.nmea_logs:
            return "; ".join(
                f"{p}: no valid fix in the NMEA log ({d.counters.summary()})"
                for p, d in zip(self.nmea_logs, self.nmea_decoders, strict=True)
            )
        if not valid_fixes:
            return f"{' '.join(map(str, self.can_logs))}: no valid fix from the gps.signals mapping"
        logs = " ".join(map(str, self.can_logs)) or "no CAN log given"
        return f"{logs}: no CAN samples of the mapped signals (can.signals) in {self.log_stats.frames} frames"

    def _can_samples(self, decoder: CanDecoder) -> Iterator[Sample]:
        gps = self.config.gps
        for msg in self._frames:
            for s in decoder.decode(msg):
                yield stamp_fix(s, gps) if isinstance(s, GnssFix) else s
        for fix in decoder.flush():
            yield stamp_fix(fix, gps)


def log_samples(config: Config, can_log: Paths, nmea_log: Paths, offset_s: float = 0.0) -> Iterator[Sample]:
    """All decoded samples of a recorded drive, time-ordered (either kind of log may be absent; see
    :class:`RecordedDrive`)."""
    return RecordedDrive(config, can_log, nmea_log, offset_s).samples()


class PacedReplay:
    """An async iterator over ``samples`` that waits so that sample times advance ``speed`` times real time.

    ``speed <= 0`` replays as fast as possible (still yielding to the event loop between samples).
    """

    def __init__(self, samples: Iterable[Sample], speed: float = 0.0) -> None:
        self._it = iter(samples)
        self.speed = speed
        self._t0: float | None = None
        self._wall0 = 0.0

    def __aiter__(self) -> AsyncIterator[Sample]:
        return self

    async def __anext__(self) -> Sample:
        try:
            sample = next(self._it)
        except StopIteration:
            raise StopAsyncIteration from None
        loop = asyncio.get_running_loop()
        if self.speed > 0.0:
            if self._t0 is None:
                self._t0, self._wall0 = sample.t, loop.time()
            delay = self._wall0 + (sample.t - self._t0) / self.speed - loop.time()
            await asyncio.sleep(max(delay, 0.0))
        else:
            await asyncio.sleep(0)
        return sample

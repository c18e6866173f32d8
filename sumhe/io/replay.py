"""Replay of recorded drives: a CAN log and an NMEA log merged into one time-ordered stream.

The stream is the same type the live sources produce (an async iterator of :data:`sumhe.messages.Sample`), so
downstream code cannot tell a replay from a car. Pacing is as fast as possible (``speed=0``), real time (``1``)
or any factor, like ``can.MessageSync``; the NMEA clock may be shifted against the CAN clock by ``offset_s``.
"""

from __future__ import annotations

import asyncio
import dataclasses
import heapq
from collections.abc import AsyncIterator, Iterable, Iterator
from pathlib import Path

from sumhe.config import Config
from sumhe.io.can import CanDecoder, read_log
from sumhe.io.fixtime import stamp_fix
from sumhe.io.nmea import iter_fixes
from sumhe.messages import GnssFix, Sample


def merge_by_time(*streams: Iterable[Sample]) -> Iterator[Sample]:
    """Merge time-ordered streams into one, ordered by ``t`` (stable: ties keep stream order)."""
    return heapq.merge(*streams, key=lambda s: s.t)


def shift_fixes(fixes: Iterable[GnssFix], offset_s: float) -> Iterator[GnssFix]:
    """Move GNSS fixes onto the CAN clock: ``t + offset_s``."""
    if offset_s == 0.0:
        yield from fixes
        return
    for fix in fixes:
        yield dataclasses.replace(fix, t=fix.t + offset_s)


def log_samples(config: Config, can_log: Path | None, nmea_log: Path | None, offset_s: float = 0.0) -> Iterator[Sample]:
    """All decoded samples of a recorded drive, time-ordered (either log may be absent).

    The NMEA receive times are moved by ``offset_s`` onto the CAN clock, then each fix is stamped with its
    measurement time (:func:`~sumhe.io.fixtime.stamp_fix`) before merging, so the stream is in measurement order.
    """
    streams: list[Iterable[Sample]] = []
    if can_log is not None:
        decoder = CanDecoder.from_config(config)
        streams.append(s for msg in read_log(can_log) for s in decoder.decode(msg))
    if nmea_log is not None:
        fixes = shift_fixes(iter_fixes(nmea_log), offset_s)
        streams.append(stamp_fix(fix, config.gps) for fix in fixes)
    return merge_by_time(*streams)


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

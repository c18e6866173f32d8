"""What the live service fed its estimator, recorded for replay (``sumhe run --record-inputs FILE``).

One JSON line per sample, in the order the estimator took them and with the times the service gave them (a CAN
sample's receive timestamp, a fix's measurement time from :class:`~sumhe.io.fixtime.FixClock`), and when it
arrived in the service's inbox and when its push began (``time.monotonic()``: the wait between is what a CAN
sample spent behind the estimator, e.g. behind a GNSS epoch's solve): a replay of the
file through a :class:`~sumhe.service.pipeline.Pipeline` gives the service's estimates again, one for one, so a
difference between the live output and a replay of the drive's own logs can be split into what the service was fed
(receive times, jitter, order) and what it did with it (``sumhe bench live`` does both). Floats are written as
``repr`` writes them, so they read back bit for bit.
"""

from __future__ import annotations

import dataclasses
import datetime as dt
import json
import math
import os
import queue
import threading
from collections.abc import Iterator
from typing import Any, NamedTuple

from sumhe.messages import CanSample, GnssFix, Sample


class Recorded(NamedTuple):
    """One recorded input: the sample, when it arrived in the service's inbox and when its push began
    (``time.monotonic()`` s; NaN where not recorded)."""

    sample: Sample
    arrived: float = math.nan
    pushed: float = math.nan


def encode(sample: Sample, arrived: float = math.nan, pushed: float = math.nan) -> str:
    """One JSON line (without the newline) for ``sample`` and its times (:class:`Recorded`)."""
    item: dict[str, Any]
    if isinstance(sample, CanSample):
        item = {"can": sample.quantity, "t": sample.t, "value": sample.value}
    else:
        fields: dict[str, Any] = dataclasses.asdict(sample)
        if sample.time_utc is not None:
            fields["time_utc"] = sample.time_utc.isoformat()
        item = {"fix": fields}
    return json.dumps({**item, "arrived": arrived, "pushed": pushed})


def decode(line: str) -> Recorded:
    """The input of one line :func:`encode` wrote (ValueError for anything else)."""
    try:
        item = json.loads(line)
        times = (float(item.get("arrived", math.nan)), float(item.get("pushed", math.nan)))
        if "can" in item:
            return Recorded(CanSample(float(item["t"]), str(item["can"]), float(item["value"])), *times)
        fields = dict(item["fix"])
        if fields.get("time_utc") is not None:
            fields["time_utc"] = dt.datetime.fromisoformat(fields["time_utc"])
        return Recorded(GnssFix(**fields), *times)
    except (KeyError, TypeError, AttributeError, json.JSONDecodeError) as err:
        raise ValueError(f"not a recorded input: {line[:80]!r}") from err


def read_records(path: str | os.PathLike[str]) -> Iterator[Recorded]:
    """The inputs of a file :class:`InputRecorder` wrote, in its order."""
    with open(path, encoding="utf-8") as f:
        for line in f:
            if line.strip():
                yield decode(line)


def read_inputs(path: str | os.PathLike[str]) -> Iterator[Sample]:
    """The samples of a file :class:`InputRecorder` wrote, in its order."""
    return (r.sample for r in read_records(path))


class InputRecorder:
    """Writes the samples the estimator takes to ``path`` (:func:`encode`) from a thread of its own: the estimator's
    thread only queues them (a write that waits for the disk would hold up the next estimate). ``close()`` writes
    what is queued and closes the file; it is idempotent. The queue is not bounded: a recording keeps every sample
    (150 a second from a car's CAN bus and receiver, each a line of about 60 bytes)."""

    def __init__(self, path: str | os.PathLike[str]) -> None:
        self.path = path
        self._queue: queue.SimpleQueue[Recorded | None] = queue.SimpleQueue()
        self._file = open(path, "w", encoding="utf-8")  # noqa: SIM115 (closed by the writer thread)
        self._thread = threading.Thread(target=self._write, name="sumhe-inputs", daemon=True)
        self._thread.start()

    def __call__(self, sample: Sample, arrived: float = math.nan, pushed: float = math.nan) -> None:
        self._queue.put(Recorded(sample, arrived, pushed))

    def _write(self) -> None:
        with self._file:
            while (item := self._queue.get()) is not None:
                self._file.write(encode(*item) + "\n")

    def close(self) -> None:
        if self._thread.is_alive():
            self._queue.put(None)
            self._thread.join()

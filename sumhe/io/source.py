"""The shape every live source shares: an async iterator fed by a reader thread through a bounded queue.

A subclass provides three blocking methods: ``_open()`` (acquire the device), ``_read()`` (one blocking read
returning a list of items, possibly empty on a device-level timeout) and ``_close()``. The base class runs them
in a daemon thread, reconnects with capped exponential back-off when the device vanishes (any exception from
``_open``/``_read``), and hands items to the event loop through a bounded queue that drops the OLDEST item when
full (fresh data beats complete data), counting drops. ``async for`` raises :class:`SourceTimeout` when nothing
arrived for ``receive_timeout_s``; the source keeps running, so the caller may simply continue iterating.

An open failure that retrying cannot mend (a subclass says which, in ``_permanent``: a missing driver, an
interface that does not exist at start-up) ends the reader thread; the next ``async for`` raises it as a
:class:`SourceError`, so the service stops with the message instead of retrying forever.
"""

from __future__ import annotations

import asyncio
import logging
import threading
import time
from abc import ABC, abstractmethod
from collections import deque
from collections.abc import AsyncIterator
from dataclasses import dataclass
from typing import Generic, TypeVar

from sumhe.errors import SourceError

log = logging.getLogger(__name__)

REPEAT_LOG_S = 60.0
"""The same open or read failure, repeating while a device is away, is logged at most this often (s)."""

T = TypeVar("T")


class SourceTimeout(SourceError, TimeoutError):
    """Nothing was received within the source's receive timeout."""


@dataclass
class SourceStats:
    """Counters of one source (read by the status line)."""

    received: int = 0
    dropped: int = 0
    reconnects: int = 0
    errors: int = 0
    connected: bool = False
    """The device was open when last seen: False from a failure until it reopens; a stop leaves it as it was (so
    the final status tells a source that was up at the end from one that was down)."""
    last_error: str = ""
    """The newest failure, kept after the source mended it."""
    last_received_s: float = 0.0
    """Wall-clock time (Unix s) at which the reader last read something; 0.0 before the first read (how fresh
    the input is, whatever the items' own times)."""


class Backoff:
    """Capped exponential back-off: 0.1 s, 0.2 s, 0.4 s ... up to ``cap_s``; ``reset()`` after success."""

    def __init__(self, cap_s: float, first_s: float = 0.1) -> None:
        self.cap_s = cap_s
        self.first_s = min(first_s, cap_s)
        self._next = self.first_s

    def next_delay(self) -> float:
        delay = self._next
        self._next = min(self._next * 2.0, self.cap_s)
        return delay

    def reset(self) -> None:
        self._next = self.first_s


async def wait_event(event: asyncio.Event, timeout_s: float) -> bool:
    """Wait for ``event`` at most ``timeout_s``: whether it was set. A cancellation always propagates
    (``asyncio.wait_for`` on Python 3.11 swallows one that comes as the event is set: the waiting task goes on)."""
    waiter = asyncio.ensure_future(event.wait())
    try:
        done, _ = await asyncio.wait({waiter}, timeout=timeout_s)
    finally:
        waiter.cancel()
    return bool(done)


class DropOldestQueue(Generic[T]):
    """A bounded thread-to-asyncio queue that drops the oldest item when full."""

    def __init__(self, maxsize: int, stats: SourceStats) -> None:
        if maxsize <= 0:
            raise ValueError("maxsize: must be positive")
        self._items: deque[T] = deque()
        self._maxsize = maxsize
        self._stats = stats
        self._event = asyncio.Event()
        self._error: SourceError | None = None

    def put_nowait(self, item: T) -> None:
        """Append ``item`` (event-loop thread only), dropping the oldest when full."""
        if len(self._items) >= self._maxsize:
            self._items.popleft()
            self._stats.dropped += 1
        self._items.append(item)
        self._event.set()

    def fail(self, error: SourceError) -> None:
        """The source has ended with ``error`` (event-loop thread only): ``get`` raises it once drained."""
        self._error = error
        self._event.set()

    async def get(self, timeout_s: float) -> T:
        """Next item; :class:`SourceTimeout` after ``timeout_s`` with nothing; the source's error if it ended."""
        while not self._items:
            if self._error is not None:
                raise self._error
            self._event.clear()
            if not await wait_event(self._event, timeout_s):
                raise SourceTimeout(f"nothing received for {timeout_s:g} s")
        return self._items.popleft()

    def __len__(self) -> int:
        return len(self._items)


class ThreadedSource(ABC, Generic[T]):
    """Base of the live sources: async context manager and async iterator (see the module docstring)."""

    name = "source"

    def __init__(self, receive_timeout_s: float, queue_size: int, reconnect_max_s: float) -> None:
        self.receive_timeout_s = receive_timeout_s
        self.stats = SourceStats()
        self._queue_size = queue_size
        self._backoff = Backoff(reconnect_max_s)
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._queue: DropOldestQueue[T] | None = None
        self._loop: asyncio.AbstractEventLoop | None = None
        self._next_repeat_log = 0.0

    @abstractmethod
    def _open(self) -> None:
        """Blocking; runs in the reader thread."""

    @abstractmethod
    def _read(self) -> list[T]:
        """Blocking; runs in the reader thread."""

    @abstractmethod
    def _close(self) -> None:
        """Blocking; runs in the reader thread."""

    def _explain(self, err: Exception) -> str:
        """What an open or read failure means, for the log (subclasses add the device and the fix)."""
        return str(err)

    def _permanent(self, err: Exception, connected_before: bool) -> bool:
        """Whether an open failure cannot mend by retrying (then the source ends with it); never, by default."""
        return False

    def counters(self) -> dict[str, object]:
        """The source's counters for the status line (subclasses add their decoder's)."""
        return vars(self.stats)

    async def start(self) -> None:
        """Start the reader thread (idempotent)."""
        if self._thread is not None:
            return
        self._loop = asyncio.get_running_loop()
        self._queue = DropOldestQueue(self._queue_size, self.stats)
        self._stop.clear()
        self._thread = threading.Thread(target=self._run, name=f"sumhe-{self.name}", daemon=True)
        self._thread.start()

    async def close(self) -> None:
        """Stop the reader thread and release the device (idempotent)."""
        self._stop.set()
        thread, self._thread = self._thread, None
        if thread is not None:
            await asyncio.to_thread(thread.join, 2.0)
            if thread.is_alive():
                log.warning("%s: reader thread did not stop within 2 s", self.name)

    async def __aenter__(self) -> ThreadedSource[T]:
        await self.start()
        return self

    async def __aexit__(self, *exc: object) -> None:
        await self.close()

    def __aiter__(self) -> AsyncIterator[T]:
        return self

    async def __anext__(self) -> T:
        if self._queue is None:
            await self.start()
        assert self._queue is not None
        return await self._queue.get(self.receive_timeout_s)

    def _deliver(self, items: list[T]) -> None:
        assert self._queue is not None
        for item in items:
            self._queue.put_nowait(item)

    def _run(self) -> None:
        assert self._loop is not None
        connected_before = False
        while not self._stop.is_set():
            try:
                self._open()
            except Exception as e:  # retried unless the subclass says it cannot mend
                if self._permanent(e, connected_before):
                    self._end(SourceError(f"{self.name}: {self._explain(e)}"))
                    return
                self._note_failure("open", e)
                continue
            connected_before = True
            self.stats.connected = True
            self._backoff.reset()
            log.info("%s: connected", self.name)
            failure: Exception | None = None
            try:
                while not self._stop.is_set():
                    items = self._read()
                    if items:
                        self.stats.received += len(items)
                        self.stats.last_received_s = time.time()
                        self._loop.call_soon_threadsafe(self._deliver, items)
            except Exception as e:  # the device vanished or failed: down; close first, then back off and reopen
                failure = e
                self.stats.connected = False
            finally:
                self._safe_close()  # on a stop too, which leaves ``connected`` as it was (the final status)
            if failure is not None:
                self._note_failure("read", failure)

    def _end(self, error: SourceError) -> None:
        self.stats.errors += 1
        self.stats.last_error = str(error)
        assert self._loop is not None and self._queue is not None
        self._loop.call_soon_threadsafe(self._queue.fail, error)

    def _note_failure(self, what: str, err: Exception) -> None:
        """Count, log (a new failure at once, the same one again at most every ``REPEAT_LOG_S``), back off."""
        self.stats.errors += 1
        last, self.stats.last_error = self.stats.last_error, f"{what}: {err}"
        delay = self._backoff.next_delay()
        self.stats.reconnects += 1
        now = time.monotonic()
        if self.stats.last_error != last or now >= self._next_repeat_log:
            self._next_repeat_log = now + REPEAT_LOG_S
            log.warning(
                "%s: %s failed: %s; retrying in %.1f s (%d failures so far)",
                self.name,
                what,
                self._explain(err),
                delay,
                self.stats.errors,
            )
        self._stop.wait(delay)

    def _safe_close(self) -> None:
        try:
            self._close()
        except Exception as e:  # closing a vanished device may fail; nothing more to do
            log.debug("%s: close failed: %s", self.name, e)

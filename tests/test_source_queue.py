"""The live sources' queue between the reader thread and the event loop: its timeout and its cancellation."""

from __future__ import annotations

import asyncio

import pytest

from sumhe.io.source import DropOldestQueue, SourceStats, SourceTimeout


def test_a_get_cancelled_as_an_item_arrives_is_cancelled_not_answered():
    """A service stopping cancels its readers; an item arriving in the same turn of the loop must not swallow the
    cancellation (``asyncio.wait_for`` does on Python 3.11 and the reader then never ended: the daemon hung)."""

    async def main() -> None:
        queue: DropOldestQueue[int] = DropOldestQueue(4, SourceStats())
        reader = asyncio.create_task(queue.get(10.0))
        await asyncio.sleep(0)  # the reader waits on the queue
        queue.put_nowait(1)
        reader.cancel()
        with pytest.raises(asyncio.CancelledError):
            await reader
        assert len(queue) == 1  # the item is still there for whoever reads next

    asyncio.run(main())


def test_get_answers_items_in_order_and_times_out_when_empty():
    async def main() -> None:
        stats = SourceStats()
        queue: DropOldestQueue[int] = DropOldestQueue(2, stats)
        for i in range(3):
            queue.put_nowait(i)
        assert stats.dropped == 1
        assert [await queue.get(1.0), await queue.get(1.0)] == [1, 2]
        with pytest.raises(SourceTimeout, match=r"nothing received for 0\.05 s"):
            await queue.get(0.05)
        later = asyncio.get_running_loop().call_later(0.05, queue.put_nowait, 7)
        assert await queue.get(5.0) == 7
        later.cancel()

    asyncio.run(main())

"""An estimator's counters, each logged as it grows (:class:`Tally`): the front-end, its sensor check and the
estimators count into the same one."""

from __future__ import annotations

import logging
import math
from collections import Counter


class Tally:
    """Counters of one estimator (its ``stats()``), logged on its module's logger at the 1st, 10th, 100th, ...
    occurrence of each (at ``level``: a warning unless the caller says otherwise)."""

    def __init__(self, name: str, logger: logging.Logger) -> None:
        self.name = name
        self.log = logger
        self.counts: Counter[str] = Counter()

    def count(self, key: str, msg: str, *args: object, level: int = logging.WARNING) -> None:
        self.counts[key] += 1
        n = self.counts[key]
        if n == 10 ** int(math.log10(n)):
            self.log.log(level, "%s: " + msg + " (%d so far)", self.name, *args, n)

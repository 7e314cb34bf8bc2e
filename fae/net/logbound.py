"""Server log records bounded in size.

Much of what the server logs comes from clients (task names, ids, parameters, paths,
tokens), so one client could otherwise write megabytes per line into the log. Every
record of the "fae.net" logger is cut here, whatever put the client's text into it:
a run of more than MAX_WORD non-blank characters keeps its start and says how long it
was, and a whole message keeps its first MAX_MESSAGE characters.

Clients also choose how often the server logs (every refused connection, every bad task),
so records are rationed too: a burst of BURST records passes, then RATE a second; the
records left out are counted, and the next record that passes says how many.
"""

from __future__ import annotations

import logging
import re
import time

MAX_WORD = 80
MAX_MESSAGE = 1000
MAX_TRACEBACK = 8000
BURST = 100
RATE = 10.0  # records a second, after a burst

_LONG_WORD = re.compile(r"\S{%d,}" % (MAX_WORD + 1))


def bounded(text: str, limit: int = MAX_MESSAGE) -> str:
    """`text` with long words and the whole cut to size (see the module docstring)."""
    text = _LONG_WORD.sub(lambda m: f"{m[0][:MAX_WORD // 2]}...[{len(m[0])} characters]", text)
    return text if len(text) <= limit else f"{text[:limit]}...[{len(text)} characters]"


class BoundedRecords(logging.Filter):
    """A logging filter that bounds each record's message (and traceback) in place and
    rations how many records pass (see the module docstring)."""

    def __init__(self, burst: int = BURST, rate: float = RATE) -> None:
        super().__init__()
        self.burst, self.rate = burst, rate
        self._tokens = float(burst)
        self._last = time.monotonic()
        self._left_out = 0

    def filter(self, record: logging.LogRecord) -> bool:
        now = time.monotonic()
        self._tokens = min(self.burst, self._tokens + (now - self._last) * self.rate)
        self._last = now
        if self._tokens < 1.0:
            self._left_out += 1
            return False
        self._tokens -= 1.0
        message = bounded(record.getMessage())
        if self._left_out:
            message += f" ({self._left_out} log records left out before this one: more than {self.rate:g} a second)"
            self._left_out = 0
        record.msg, record.args = message, None
        if record.exc_info and not record.exc_text:
            record.exc_text = bounded(logging.Formatter().formatException(record.exc_info), MAX_TRACEBACK)
        return True


def bound_logger(name: str = "fae.net") -> None:
    """Bound every record of logger `name` (once, however often it is called)."""
    logger = logging.getLogger(name)
    if not any(isinstance(f, BoundedRecords) for f in logger.filters):
        logger.addFilter(BoundedRecords())

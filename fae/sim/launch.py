"""Warp launch helpers shared by the solver and the skin output: first calls one at a time,
and recorded launches kept by the arrays they were recorded with.

    call_first_alone(key, fn)       run fn() once per key and process, never two at once
    LaunchCache(size).get(owners, record)   a recorded launch per tuple of objects
"""

from __future__ import annotations

import threading
from collections import OrderedDict

_LAUNCH_CACHE_SIZE = 16

_first_calls_lock = threading.Lock()
_first_calls_done: set = set()


def call_first_alone(key, fn) -> None:
    """Run fn() unless a call for `key` already finished in this process; no two such
    first calls run at once, and later ones wait for the first to finish.

    Warp's CPU backend crashed (a segfault inside the kernel) when threads entered a kernel
    for the first time at once: ten faces of `fae serve` stepping their first frames
    together crashed the server in 4 of 6 runs. Once each kernel has run, faces step in
    several threads safely. Solvers and skin outputs run their kernels once through this
    when made (fae.sim.skin)."""
    if key in _first_calls_done:
        return
    with _first_calls_lock:
        if key not in _first_calls_done:
            fn()
            _first_calls_done.add(key)


class LaunchCache:
    """Recorded launches (or tuples of them) by the objects whose arrays they were recorded
    with, the `size` most recently used. An entry keeps those objects alive, so that the ids
    in its key cannot be reused by others while it is cached."""

    def __init__(self, size: int = _LAUNCH_CACHE_SIZE):
        self.size = size
        self._entries: OrderedDict[tuple, tuple] = OrderedDict()

    def get(self, owners: tuple, record):
        """The entry for `owners` (a tuple of objects), made by `record()` if new."""
        key = tuple(id(o) for o in owners)
        entry = self._entries.get(key)
        if entry is None:
            entry = self._entries[key] = (record(), owners)
            while len(self._entries) > self.size:
                self._entries.popitem(last=False)
        else:
            self._entries.move_to_end(key)
        return entry[0]

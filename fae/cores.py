"""How many threads fae's side-by-side work may use.

    usable_cores() -> int       the cores this process may run on
    workers(at_most) -> int     threads for work split side by side
"""

from __future__ import annotations

import os


def usable_cores() -> int:
    """The cores this process may run on: its CPU affinity where the OS has one (a
    container or `taskset` may allow fewer than the machine has), else the machine's."""
    return len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else (os.cpu_count() or 1)


def workers(at_most: int) -> int:
    """Threads for independent pieces of work run side by side: one per usable core, at
    most `at_most`, at least one."""
    return max(1, min(at_most, usable_cores()))

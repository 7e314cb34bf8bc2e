"""What native libraries print on file descriptor 2, filtered before a user sees it.

Warp's and MediaPipe's C++ cores write to the process's stderr directly, whatever Python
asks (Warp's "could not find or load the NVIDIA CUDA driver" on every machine without
one, where fae runs on the CPU by design; MediaPipe's absl and TFLite start-up lines):
fae's own messages on stderr must stay readable.

    with native_stderr_filtered(keep=lambda line: "CUDA driver" not in line):
        wp.init()
"""

from __future__ import annotations

import os
import sys
import tempfile
from collections.abc import Callable, Iterator
from contextlib import contextmanager


@contextmanager
def native_stderr_filtered(keep: Callable[[str], bool] = lambda line: False) -> Iterator[None]:
    """Meanwhile, descriptor 2 goes to a temporary file; after, its lines that `keep`
    accepts are written back to stderr (by default none). Without a descriptor 2 (closed,
    or an embedding host) or a temporary file, nothing is redirected. Keep the block
    short: should the process die inside it, what it printed there is lost."""
    try:
        if sys.stderr is not None:
            sys.stderr.flush()
        caught = tempfile.TemporaryFile(mode="w+b")
    except (OSError, ValueError):  # no temporary file to be had: nothing is filtered
        yield
        return
    try:
        saved = os.dup(2)
    except OSError:  # no descriptor 2 (closed, or an embedding host): nothing to filter
        caught.close()
        yield
        return
    with caught:
        try:
            os.dup2(caught.fileno(), 2)
            yield
        finally:
            os.dup2(saved, 2)
            os.close(saved)
            caught.seek(0)
            kept = [line for line in caught.read().decode("utf-8", "replace").splitlines(keepends=True)
                    if keep(line)]
            if kept and sys.stderr is not None:
                sys.stderr.write("".join(kept))
                sys.stderr.flush()

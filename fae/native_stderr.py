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
    accepts are written back to stderr (by default none). Without a real descriptor 2
    (an embedding host) nothing is redirected."""
    try:
        sys.stderr.flush()
        saved = os.dup(2)
    except (OSError, ValueError):
        yield
        return
    with tempfile.TemporaryFile(mode="w+b") as caught:
        try:
            os.dup2(caught.fileno(), 2)
            yield
        finally:
            os.dup2(saved, 2)
            os.close(saved)
            caught.seek(0)
            for line in caught.read().decode("utf-8", "replace").splitlines(keepends=True):
                if keep(line):
                    sys.stderr.write(line)
            sys.stderr.flush()

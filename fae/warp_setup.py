"""Warp, configured once for all of fae's kernels (import `wp` from here).

fae runs its CPU kernels from several threads at once (a server's faces step on a pool of
threads; Warp releases the interpreter lock during a launch). The first launches of the
kernels that run per frame (the solver's and the skin's) are made alone
(fae.sim.launch.call_first_alone): concurrent first launches, which also load their
module, crashed; the kernels used while a head is built run under the server's face
factory lock (fae.net.faces.player_face_factory). And on
x86-64, Warp's default (`config.enable_tiles_in_stack_memory` True) points one static
variable, shared by all threads, at the running launch's tile storage, and every launch
writes through it as it starts: with two launches at once, that write can land in another
thread's stack. fae's kernels use no tiles, so the option is left to Warp's automatic
choice, which enables it only on AArch64, where the pointer lives in a register of each
thread.

    launch_split(kernel, n, inputs, outputs) -> one kernel's samples on up to SPLIT_THREADS cores
"""

import os
import sys
import threading
from concurrent.futures import ThreadPoolExecutor

import numpy as np
import warp as wp

from fae.cores import workers
from fae.native_stderr import native_stderr_filtered
from fae.private_folder import private_temporary_folder

SPLIT_THREADS = 4  # at most, for one launch's samples side by side
SPLIT_MIN = 2048  # samples below which a launch is not split (a thread costs more than it saves)

wp.config.enable_tiles_in_stack_memory = None
# Warp reports every module load on stdout at its default level; a player's output is the
# user's, so keep to warnings and errors.
wp.config.log_level = 30
# Its native core says on stderr, on every machine without an NVIDIA driver, that the GPU
# will not be available: fae runs on the CPU by default and refuses `--device cuda` without
# one in its own words, so that line is left out (anything else it says is kept)
with native_stderr_filtered(keep=lambda line: "NVIDIA CUDA driver" not in line):
    try:
        wp.init()
    except OSError as exc:
        # Warp keeps compiled kernels under the user's cache folder; where that cannot be
        # made (a read-only home) every command that runs a kernel stopped with a traceback
        fallback = private_temporary_folder("fae-warp-cache")
        print(f"fae: Warp's kernel cache cannot be made ({exc.strerror or exc}: {exc.filename or '?'}); using "
              f"{fallback} instead (WARP_CACHE_PATH chooses it)", file=sys.stderr)
        wp.config.kernel_cache_dir = fallback
        try:
            wp.init()
        except OSError as again:
            raise SystemExit(f"fae: Warp cannot start: no kernel cache folder can be made ({again}); set "
                             "WARP_CACHE_PATH to a writable folder") from None



def launch_split(kernel, n: int, inputs: list, outputs: list, device: str = "cpu") -> None:
    """Launch `kernel` over samples 0..n-1; its arguments are `inputs`, then the first
    sample of the launch (int: the kernel's sample is wp.tid() + first), then `outputs`.
    On the CPU a launch runs on one core: from SPLIT_MIN samples on, they are split into
    one range per usable core (at most SPLIT_THREADS), launched side by side (Warp lets go
    of the GIL while a kernel runs)."""
    parts = 1 if wp.get_device(device).is_cuda or n < SPLIT_MIN else workers(SPLIT_THREADS)
    bounds = np.linspace(0, n, parts + 1).astype(int)

    def run(k: int) -> None:
        if bounds[k + 1] > bounds[k]:
            wp.launch(kernel, dim=int(bounds[k + 1] - bounds[k]), device=device,
                      inputs=[*inputs, int(bounds[k]), *outputs])

    if parts == 1:
        run(0)
        return
    wp.load_module(kernel.module, device=device)  # loaded once, before two threads would both load it
    # the calling thread runs the first range, threads kept for the purpose the others (a pool
    # made per call cost 1-2 ms of thread starts, a fit makes about a hundred such launches)
    rest = _submitted(parts - 1, run, range(1, parts))
    try:
        run(0)
    finally:
        for launched in rest:
            launched.result()


_split_pools: dict[int, ThreadPoolExecutor] = {}
_split_pools_lock = threading.Lock()


def _submitted(threads: int, run, ranges) -> list:
    """Futures of run(k) for each k of `ranges`, on the process's pool of `threads` threads
    for launch_split's further ranges (made on first use). Submitted under the pools' lock:
    a pool that stop_split_pools lets go has every range it was given done first, and gets
    no more."""
    with _split_pools_lock:
        pool = _split_pools.get(threads)
        if pool is None:
            pool = _split_pools[threads] = ThreadPoolExecutor(threads, thread_name_prefix="fae-split")
        return [pool.submit(run, k) for k in ranges]


def stop_split_pools() -> None:
    """Let the pools' threads go (each is idle once launch_split returns); a later launch
    makes new ones. The `fae` command does so before it exits (fae.cli.run): it skips
    Python's teardown only when no thread of the command is left running."""
    with _split_pools_lock:
        pools = list(_split_pools.values())
        _split_pools.clear()
    for pool in pools:
        pool.shutdown(wait=True)


def _forget_split_pools() -> None:
    # a forked child has none of its parent's threads: its pools are made anew
    global _split_pools_lock
    _split_pools.clear()
    _split_pools_lock = threading.Lock()


os.register_at_fork(after_in_child=_forget_split_pools)


__all__ = ["launch_split", "stop_split_pools", "wp"]

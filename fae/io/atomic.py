"""Outputs appear only when complete: write to a temporary file beside the target, then rename.

The temporary file is named `.NAME.PID.XXXXXXXX.SUFFIX` (hidden, beside the target NAME),
and is removed on any exception, SIGINT and SIGTERM included (fae.cli turns SIGTERM into
an exception). A process killed outright (SIGKILL, power loss) cannot remove its own, so
the next write of the same target sweeps the temporary files of that target whose
writer, named by PID, is no longer running.
"""

from __future__ import annotations

import contextlib
import errno
import os
import re
import shutil
import stat
import tempfile
from pathlib import Path
from typing import Iterator


_WRITE_FAILED = (errno.ENOSPC, errno.EDQUOT, errno.EFBIG, errno.EIO)


class OutputError(OSError):
    """An output that cannot be written where it was asked for; the message names it."""


def _running(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:  # someone else's process
        return True
    return True


# what a temporary name adds after ".NAME.": the writer's pid (at most 7 digits: Linux's
# pid_max is 4194304) and tempfile's 8 random characters; a user's ".face.glb.20241105.final.glb"
# or ".frames.2024.backup" is no temporary file and is never swept
_TEMP_TAIL = r"(\d{1,7})\.[a-z0-9_]{8}"


def sweep_stale(path: str | os.PathLike) -> list[Path]:
    """Remove the temporary files of `path` left by writers that are no longer running;
    returns them. Files of running writers (this process included) are left alone."""
    target = Path(path)
    folder = target.parent if str(target.parent) else Path(".")
    pattern = re.compile(r"\." + re.escape(target.name) + r"\." + _TEMP_TAIL + r"\.[A-Za-z0-9]+\Z")
    removed = []
    try:
        entries = list(os.scandir(folder))
    except OSError:
        return removed
    for entry in entries:
        match = pattern.match(entry.name)
        if match is None or not entry.is_file(follow_symlinks=False):
            continue
        pid = int(match.group(1))
        if pid == os.getpid() or _running(pid):
            continue
        with contextlib.suppress(FileNotFoundError):
            os.unlink(entry.path)
            removed.append(Path(entry.path))
    return removed


def staging_folder(folder: str | os.PathLike, name: str) -> Path:
    """A new hidden folder `.NAME.PID.XXXX` in `folder` for files that replace others only
    when all are written; the ones left by writers no longer running are removed first."""
    folder = Path(folder)
    pattern = re.compile(r"\." + re.escape(name) + r"\." + _TEMP_TAIL + r"\Z")
    with contextlib.suppress(OSError):
        for entry in os.scandir(folder):
            match = pattern.match(entry.name)
            if match and entry.is_dir(follow_symlinks=False) and not _running(int(match.group(1))):
                shutil.rmtree(entry.path, ignore_errors=True)
    return Path(tempfile.mkdtemp(prefix=f".{name}.{os.getpid()}.", dir=folder))


def special_file(path: str | os.PathLike) -> str | None:
    """What `path` is when it exists and is neither a regular file nor a folder (followed
    through links): "a device", "a named pipe", "a socket"; else None. The rename that puts an
    output in place would replace it with a plain file (as root, /dev/null itself)."""
    try:
        mode = os.stat(path).st_mode
    except (OSError, ValueError):
        return None
    if stat.S_ISREG(mode) or stat.S_ISDIR(mode):
        return None
    if stat.S_ISCHR(mode) or stat.S_ISBLK(mode):
        return "a device"
    if stat.S_ISFIFO(mode):
        return "a named pipe"
    if stat.S_ISSOCK(mode):
        return "a socket"
    return "not a regular file"


@contextlib.contextmanager
def atomic_path(path: str | os.PathLike, suffix: str | None = None, sweep: bool = True) -> Iterator[Path]:
    """Yield a temporary path in the target's folder; rename it onto `path` on success.

    On any exception the temporary file is removed and `path` is left untouched.
    `suffix` defaults to the target's own suffix (some writers pick the format from it).
    sweep  first remove the target's stale temporary files (see `sweep_stale`); writers of
           many files into one folder (a frame per PNG) pass False: each sweep lists the folder.
    An output that is a link is replaced by the file, the file it pointed to left alone
    (following it would let whoever can plant a link in a shared folder aim fae's output
    at a file of the user's).
    Raises FileNotFoundError when the folder does not exist, OutputError (an OSError
    naming the target) when it cannot take a file or is a device, pipe or socket.
    """
    target = Path(path)
    kind = special_file(target)
    if kind is not None:
        raise OutputError(f"{target}: is {kind}, not a file; expected a file name to write")
    folder = target.parent if str(target.parent) else Path(".")
    if not folder.is_dir():
        raise FileNotFoundError(f"{target}: output folder {folder} does not exist")
    if sweep:
        sweep_stale(target)
    try:
        fd, tmp = tempfile.mkstemp(prefix=f".{target.name}.{os.getpid()}.",
                                   suffix=suffix if suffix is not None else target.suffix, dir=folder)
    except OSError as exc:
        raise OutputError(f"{target}: cannot write a file in {folder} ({exc.strerror or exc})") from None
    os.close(fd)
    tmp_path = Path(tmp)
    try:
        # mkstemp creates 0600 files; an output should get the ordinary umask-based mode.
        umask = os.umask(0)
        os.umask(umask)
        os.chmod(tmp_path, 0o666 & ~umask)
        try:
            yield tmp_path
        except OSError as exc:  # a full disk says nothing of which file: name the output
            writing = exc.filename in (tmp, str(tmp_path)) or (exc.filename is None and exc.errno in _WRITE_FAILED)
            if isinstance(exc, OutputError) or not writing:  # an input's own error names the input
                raise
            failed = OutputError(f"{target}: cannot be written ({exc.strerror or exc})")
            failed.errno = exc.errno  # a caller may still tell a full disk
            raise failed from None
        try:
            os.replace(tmp_path, target)
        except OSError as exc:  # a folder where the file should go: name the file, not the temporary one
            raise OutputError(f"{target}: cannot be replaced ({exc.strerror or exc})") from None
    except BaseException:
        with contextlib.suppress(FileNotFoundError):
            tmp_path.unlink()
        raise


@contextlib.contextmanager
def atomic_open(path: str | os.PathLike, mode: str = "w", **kwargs) -> Iterator:
    """`open()` whose result appears at `path` only when the block completes without error."""
    with atomic_path(path) as tmp, open(tmp, mode, **kwargs) as handle:
        yield handle

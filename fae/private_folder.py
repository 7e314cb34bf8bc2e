"""A folder of the system's temporary directory that only this user can write, for caches a
library keeps under a home folder that cannot be written (a read-only home, a service user)."""

from __future__ import annotations

import os
import tempfile


def private_temporary_folder(prefix: str) -> str:
    """`<tmp>/<prefix>-<uid>`, made 0700 where it is missing, the same one each run where it
    can be (a cache then fills once); a folder someone else made first, a link, or one others
    can write is not used: a fresh `mkdtemp` folder instead."""
    uid = getattr(os, "getuid", lambda: None)()
    path = os.path.join(tempfile.gettempdir(), f"{prefix}-{uid if uid is not None else 'user'}")
    try:
        os.makedirs(path, mode=0o700, exist_ok=True)
        st = os.lstat(path)
        if (os.path.islink(path) or not os.path.isdir(path) or (uid is not None and st.st_uid != uid)
                or st.st_mode & 0o077):
            raise PermissionError(path)
        return path
    except OSError:
        return tempfile.mkdtemp(prefix=f"{prefix}-")


def writable_folder(path: str) -> bool:
    """Whether folder `path` exists or can be made, and this user can write it."""
    try:
        os.makedirs(path, exist_ok=True)
    except OSError:
        return False
    return os.access(path, os.W_OK | os.X_OK)

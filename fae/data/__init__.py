"""Data the product needs at run time, shipped inside the package (wheel and checkout alike).

    shipped_head_path() -> Path    the generic head fae plays when no head is given

`$FAE_TEMPLATES`, when set, names a folder whose generic_head.glb replaces the packaged
one (a head rebuilt elsewhere, or a site's own default head).
"""

from __future__ import annotations

import atexit
import contextlib
import os
from importlib import resources
from pathlib import Path

HEAD_NAME = "generic_head.glb"
TEMPLATES_VARIABLE = "FAE_TEMPLATES"

_extracted = contextlib.ExitStack()  # holds a file extracted from a zipped install until exit
atexit.register(_extracted.close)


def shipped_head_path() -> Path:
    """Where the shipped generic head is: `$FAE_TEMPLATES/generic_head.glb` when the variable
    is set, else the package's own copy. The file may be missing (a checkout whose head was
    never built, a wrong variable): callers report that, naming this path."""
    folder = os.environ.get(TEMPLATES_VARIABLE)
    if folder:
        return Path(folder) / HEAD_NAME
    resource = resources.files(__name__) / HEAD_NAME
    if isinstance(resource, Path):
        return resource
    return _extracted.enter_context(resources.as_file(resource))  # e.g. imported from a zip

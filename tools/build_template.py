"""Build the shipped generic head: `python tools/build_template.py [-o FILE]`.

Writes the shipped head, fae/data/generic_head.glb, by default (the same as `fae template build`): the head
with its calibrated FAP mapping (build, then fae.animate.calibrate). The file is
generated, never hand-edited; tests check that it equals a fresh build.
"""

from __future__ import annotations

import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from fae.cli import main  # noqa: E402

if __name__ == "__main__":
    sys.exit(main(["template", "build", *sys.argv[1:]]))

"""The skin simulation: Warp kernels (one file per physics concern) and their numpy twin."""

import fae.warp_setup  # noqa: F401  (Warp's configuration before any kernel is built)

"""The skin simulation: Warp kernels (one file per physics concern) and their numpy twin."""

import warp as wp

# Warp reports every module load on stdout at its default level; a player's output is the
# user's, so keep to warnings and errors.
wp.config.log_level = 30

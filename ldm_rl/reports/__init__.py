"""Report tools over finished runs (tables and figures from run folders and docs/results/), run from the
repository as ``python -m ldm_rl.reports.<name> --help``."""

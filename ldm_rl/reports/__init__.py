"""Report tools over finished runs (tables and figures from run folders and docs/results/), run from the
repository as ``python -m ldm_rl.reports.<name> --help``."""

import re

# a finished run kept in a results folder (docs/results/policy): curves_<task>_<agent>_seed<k>[_<tag>]_<kind>
_KEPT_RUN = r"curves_[a-z_]+?_(?P<agent>ldm|fcdqn|rs|dynaq)_seed(?P<seed>\d+)(?:_(?P<tag>[A-Za-z0-9.]+))?_"


def kept_file(kind: str) -> re.Pattern:
    """The name pattern of a kept run's ``kind`` file (``curve.csv``, ``final_metrics.json``,
    ``generalization.json``); groups ``agent``, ``seed`` and ``tag`` (None when untagged)."""
    return re.compile(_KEPT_RUN + re.escape(kind))

"""Data: expert demonstrations (``ldm_rl.data.demos``)."""

"""The four tasks of the paper, one module each."""

"""Pure algorithms: numpy in, numpy out.

Nothing in this package may import transport (zenoh, mcap, serial), read the clock
or the environment, or print; ``tests/unit/test_purity.py`` enforces it.
"""

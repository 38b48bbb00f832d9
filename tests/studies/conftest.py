"""Tests of the studies layer (``dampax._studies``): error maps (one process and several),
local and global sensitivity against finite differences and analytic indices.

Compiled programs are shared through the session's compilation cache (tests/conftest.py) and
each file's module fixtures (the maps use the settings of the kept step of
tests/reference/test_speed.py).
"""

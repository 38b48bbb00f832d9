"""Tests of the reference engine (``dampax._reference``): DOP853 with exact stick-slip against
scipy with events and exact solutions, its order of accuracy, dense output, static friction,
and the fast paths (no recompilation, kept programs).

Compiled programs are shared through the session's compilation cache (tests/conftest.py) and
each file's module fixtures (one batch shape per file).
"""

"""Tests of the models layer (``dampax._models`` and ``dampax.solve`` with the analytic models):
f(t), the matched amplitude, Coulomb half-swings and Rizcallah, cubic stiffness, the domains
and RESULTS, the atlas, gradients, and the papers' quoted numbers.

Compiled programs are shared through the session's compilation cache (tests/conftest.py) and
each file's module fixtures; ``helpers`` (tests/helpers.py: scipy's integrator with events)
is importable from every folder.
"""

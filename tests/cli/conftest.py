"""Tests of the command line (``dampax._cli`` and the ``dampax_cli`` launcher) and of
``dampax reproduce`` (the paper layer).

The commands run in process (capsys) on the programs the other tests compiled (the session's
compilation cache, tests/conftest.py); one test runs the installed console script.
"""

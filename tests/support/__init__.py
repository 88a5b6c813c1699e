"""Helpers shared by the test modules (and the benchmarks): waits on a condition with a deadline, the environment
scrub for child processes, and a launcher of module processes with one log file each.

Test modules import them as ``from support.waits import wait_for`` (pytest puts ``tests/`` on ``sys.path``, as it
has no ``__init__.py``); a test module never imports another test module.
"""

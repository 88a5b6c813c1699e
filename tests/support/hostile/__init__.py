"""Hostile brains: each tries one thing a submitted brain must not be able to do (``tests/test_sandbox.py`` runs
each in a real sandbox and checks from outside that nothing got out). Each attacks without catching what the
sandbox answers, so that the host's exit says which wall it met."""

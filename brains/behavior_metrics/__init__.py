"""Run a brain file written for JdeRobot Behavior Metrics unchanged (``--brain path/to/brain.py``)."""

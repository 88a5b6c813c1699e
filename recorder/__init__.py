"""MCAP recorder, replay and datasets. Not built yet: the recording issue (#4) fills this package."""

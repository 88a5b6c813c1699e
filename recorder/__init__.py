"""MCAP recorder, replay, and training datasets built from recordings.

``recorder.writer`` writes bus messages to MCAP (crash-safe), ``recorder.reading`` reads them back as bus
messages, ``recorder.service`` is the recorder process (``python -m recorder``), ``recorder.replay`` puts a
recording back on the bus, and ``recorder.dataset.build`` turns recordings into training datasets.
"""

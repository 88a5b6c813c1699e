"""Live view: a run's bus traffic served to Foxglove over its WebSocket protocol (``python -m services.viz``,
``drivebench view``). See ``docs/live-view.md``."""

"""The orchestrator: the local launcher, the ``drivebench`` command, run control and reports."""

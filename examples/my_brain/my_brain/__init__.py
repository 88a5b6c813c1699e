"""An example driving brain packaged on its own; drivebench finds it through the ``drivebench.brains`` entry point."""

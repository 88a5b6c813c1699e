"""Deployment: the process graph, security, configs and typed YAML, process runtime."""

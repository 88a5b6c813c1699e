"""The router: a Zenoh router in a Python process, the discovery hub of one stack."""

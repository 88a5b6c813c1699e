"""A brain that always sends the same command: a fake for tests and a floor for benchmarks."""

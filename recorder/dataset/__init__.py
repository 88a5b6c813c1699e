"""Training datasets from recordings: reading, pairing frames with commands, the format, the build."""

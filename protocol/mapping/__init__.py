"""The mapping of bus messages to recordings and viewers: MCAP encodings, topics, views."""

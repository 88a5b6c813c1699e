"""The scorer: Behavior-Metrics-compatible and metric-true episode scores from ground-truth poses."""

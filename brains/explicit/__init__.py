"""The explicit brain: Behavior Metrics' OpenCV red-line follower with a two-mode PID, at any camera size."""

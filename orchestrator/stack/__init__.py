"""Running one stack: the launcher, the process supervisor, health, progress and live swap."""

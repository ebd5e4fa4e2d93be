"""The rerun viewer: entity layout and blueprint, and the sink that logs to it."""

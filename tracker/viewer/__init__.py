"""The rerun viewer: entity layout and blueprint (layout), the sinks that log to it (sink),
and the outputs of a command (output)."""

"""The online loop: frame sources, the loop itself, and its sinks."""

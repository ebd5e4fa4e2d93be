"""The online loop: frame sources, the loop itself, its sinks, and a session that wires them."""

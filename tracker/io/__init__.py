"""Input and output: joint and estimate datagrams, OpenIGTLink, MCAP recordings."""

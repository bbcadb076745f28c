"""The simulated cell (ground truth) and the protocol-level mock servers that serve it."""

"""The radiance field: hash-grid encoding, direction encoding, density activation and the NGP field."""

"""Front ends: Gymnasium (CPU), vector (CPU), PettingZoo (CPU) and MJX (JAX)."""

"""The simulated convergence study and synthetic-scene tools."""

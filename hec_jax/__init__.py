"""hec_jax: hand-eye coordination for flexible impedance control, in JAX/MJX."""

"""hec_jax.nets"""

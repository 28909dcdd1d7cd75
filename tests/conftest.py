"""Shared pytest setup for jaxatt. Float64 everywhere: several tests check accuracy at 1e-9..1e-12."""

import jax

jax.config.update("jax_enable_x64", True)

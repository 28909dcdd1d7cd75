"""Shared pytest setup for jaxatt.

* Float64 everywhere: several tests check accuracy at 1e-9..1e-12.
* One XLA compilation cache for the whole test run (``.pytest_cache/xla`` unless ``JAX_COMPILATION_CACHE_DIR`` is
  set): the xdist workers and the CLI subprocesses that the tests start compile many of the same programs
  (the batista-so3 Monte Carlo, the tuning gradients), and XLA reuses an executable whose HLO, compile options,
  backend and jax version are identical. The cache changes no number a test sees, only how often the same
  program is compiled. Every program is written to it, however short its compile: the suite compiles ~3,400
  one-op eager programs (7 % of its compile time), the same ones in each worker, subprocess and notebook kernel
  (test_so3, test_parametrize, test_engine and test_nlio, cold cache, 2 workers: 128 / 125 s of CPU with every
  program cached against 137 / 128 s with only those over 0.5 s, two interleaved pairs).
"""

import os
from pathlib import Path

os.environ.setdefault("JAX_COMPILATION_CACHE_DIR", str(Path(__file__).resolve().parents[1] / ".pytest_cache" / "xla"))
os.environ.setdefault("JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS", "0")

import jax

jax.config.update("jax_enable_x64", True)

"""Test configuration: float64 everywhere, warnings are errors (see pyproject)."""
import jax

jax.config.update("jax_enable_x64", True)

import os

# the CLI keeps a persistent XLA cache in the user's home; tests leave no such files
os.environ.setdefault("JAXVALVE_CACHE_DIR", "off")

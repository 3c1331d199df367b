"""TABX in JAX: a vectorised, recompilation-free battle simulator for MARL and UED.

Main entry points: `tabx.env.TabxEnv` (array API), `tabx.params` (EnvConfig / EnvParams levels),
`tabx.scenarios` (scenario files), `tabx.marl` (JaxMARL-compatible adapter).

Importing `tabx` changes no environment variable and starts no JAX backend. The XLA:CPU
settings the `tabx` command uses (one CPU device per usable core, YNN fusion off) are one call
away, before JAX starts its backend: `tabx.xla_flags.apply()` (docs/performance.md).
"""

__version__ = "0.1.0"

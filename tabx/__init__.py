"""TABX in JAX: a vectorised, recompilation-free battle simulator for MARL and UED.

Main entry points: `tabx.env.TabxEnv` (array API), `tabx.params` (EnvConfig / EnvParams levels),
`tabx.scenarios` (scenario files), `tabx.marl` (JaxMARL-compatible adapter).
"""

from tabx import _xla_flags

_xla_flags.apply()

__version__ = "0.1.0"

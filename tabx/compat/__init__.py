"""Adapters that let code written for other JAX ecosystems drive the TABX simulator unchanged.

- `tabx.compat.jaxmarl`: `TabxJaxMARLEnv`, a `jaxmarl.environments.MultiAgentEnv` (needs the
  `peers` extra: `pip install "tabx-ued[peers]"`), for JaxMARL's wrappers and baseline loops,
  and `make_env(name_or_path, **env_kwargs)`, the baselines' env line;
- `tabx.compat.jaxued`: `TabxUnderspecifiedEnv` and `AutoReplayWrapper`, jaxued's
  `UnderspecifiedEnv` interface over our levels (no dependency), for jaxued-style DR / PLR /
  ACCEL loops.

See docs/ecosystem.md.
"""

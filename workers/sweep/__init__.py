"""Sweeps: the spec (`spec`), the sweep folder (`folder`), the Tune driver (`tune`), one trial
(`trial`), the live table (`table`) and the report in the paper's layout (`report`)."""

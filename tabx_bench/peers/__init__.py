"""Other simulators, run under our benchmark protocols for side by side numbers.

Each peer needs an optional dependency (the `peers` extra: `pip install -e ".[peers]"`); a
missing one raises `PeerUnavailable` with the install command, never an ImportError traceback.
"""


class PeerUnavailable(RuntimeError):
    """The peer simulator's package is not installed (message says how to install it)."""


INSTALL_HINT = ('install the optional peers extra: pip install -e ".[peers]" (jaxmarl==0.2.0); '
                "or, to keep it out of this environment, python -m venv --system-site-packages "
                "VENV && VENV/bin/pip install jaxmarl==0.2.0 and run VENV/bin/python -m tabx "
                "bench compare")

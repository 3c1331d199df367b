"""`python -m tabx ...`: the `tabx` command (`tabx_ued.cli.main`), as if typed in a shell.

The one module of the simulator package that names a layer above it: an entry point, which no
module imports (tests/project/test_layers.py exempts it by name).
"""

import sys

from tabx_ued.cli import main

if __name__ == "__main__":
    sys.exit(main())

"""`python -m tabx_ued ...` runs the `tabx` command."""

import sys

from tabx_ued.cli import main

sys.exit(main())

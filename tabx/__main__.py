"""`python -m tabx ...`: the installed `tabx` command, as if typed in a shell.

The `tabx` command is the console script the package installs (`tabx_ued.cli:main`, every
layer's commands); it is looked up through the entry point, so this simulator layer names no
layer above it. Where the package is not installed (a bare source tree on PYTHONPATH), the
simulator's own commands run (`tabx.cli.main`).
"""

import sys
from importlib.metadata import entry_points


def main() -> int:
    found = [point for point in entry_points(group="console_scripts", name="tabx")
             if point.dist is None or point.dist.name == "tabx-ued"]
    command = found[0].load() if found else None
    if command is None:
        from tabx.cli import main as command
    return int(command() or 0)


if __name__ == "__main__":
    sys.exit(main())

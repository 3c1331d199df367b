"""Converter: the reference implementation's scenario JSON -> our bundled files.

    python tools/convert_reference_scenarios.py [--reference DIR] [--out tabx/data]

Reads scenarios/{challenges,units,zones} and scenarios/eval_scenarios/{units,zones} of the
reference data (MIT, Copyright (c) 2025 TABX), writes tabx/data/scenarios/{challenges,units,
zones}/<name>.json (eval files get `"split": "eval"` in the same folders) and copies the licence
to tabx/data/LICENSE-TABX. Re-running it gives identical files.
"""

from __future__ import annotations

import argparse
import re
import sys
from dataclasses import replace
from pathlib import Path

REPO = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(REPO))

from tabx.files import atomic_write_bytes  # noqa: E402
from tabx.scenarios import read_reference_scenario, save_scenario  # noqa: E402
from tabx.scenarios.summary import composition  # noqa: E402

DEFAULT_REFERENCE = REPO.parent / "shared" / "reference" / "tabx-data"
SOURCES = (  # (reference folder, our folder, split)
    ("scenarios/challenges", "challenges", None),
    ("scenarios/units", "units", None),
    ("scenarios/eval_scenarios/units", "units", "eval"),
    ("scenarios/zones", "zones", None),
    ("scenarios/eval_scenarios/zones", "zones", "eval"),
)
UNIT_NAME = re.compile(r"^(\d+[A-Z])+vs(\d+[A-Z])+$")  # e.g. 2F1M2Avs2S1K
CREDIT = "TABX reference data (MIT, Copyright (c) 2025 TABX; see tabx/data/LICENSE-TABX)"


def convert(reference: Path, out: Path) -> list[Path]:
    written: list[Path] = []
    seen: dict[str, str] = {}
    for src, dst, split in SOURCES:
        for path in sorted((reference / src).glob("*.json")):
            if path.stem in seen:  # names must be unique across folders for load_named
                raise SystemExit(f"duplicate scenario name {path.stem}: {seen[path.stem]}, {src}")
            seen[path.stem] = src
            s = read_reference_scenario(path)
            description = f"Converted from {src}/{path.name} of the {CREDIT}."
            if s.units and UNIT_NAME.match(s.name):
                actual = f"{composition(s.allies)}vs{composition(s.enemies)}"
                if actual != s.name:  # two reference files' names lie about their content
                    description += (f" Note: the name says {s.name} but the file holds {actual}"
                                    " (kept as in the reference).")
            category = {"challenges": "challenge"}.get(dst, dst)
            s = replace(s, category=category, split=split, description=description)
            written.append(save_scenario(out / "scenarios" / dst / f"{path.stem}.json", s))
    written.append(atomic_write_bytes(out / "LICENSE-TABX", (reference / "LICENSE").read_bytes()))
    return written


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--reference", type=Path, default=DEFAULT_REFERENCE)
    parser.add_argument("--out", type=Path, default=REPO / "tabx" / "data")
    args = parser.parse_args(argv)
    written = convert(args.reference, args.out)
    print(f"wrote {len(written)} files under {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())

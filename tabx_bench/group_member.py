"""One member process of `tabx bench train --learners N` (`tabx_bench.learner_group.run_group`
starts N of them):

    python -m tabx_bench.group_member HOST:PORT N INDEX SHARE_CORES OPTIONS_JSON OUT_JSON

SHARE_CORES: 1 pins the member to its share of the machine's cores (`share_cores`), 0 not.
"""

from __future__ import annotations

import dataclasses
import json
import sys
from pathlib import Path
from typing import Any


def member(address: str, learners: int, index: int, sharing_cores: bool,
           options: dict[str, Any], out: str) -> None:
    """Member INDEX of a group of N: its own share of the cores where asked (`share_cores`),
    the `tabx` command's XLA settings (its share of the cores as devices, set by `run_group`),
    then the group and the benchmark."""

    from ued.learners import distributed

    if sharing_cores:
        distributed.share_cores(index, learners)
    from tabx import xla_flags

    xla_flags.apply()

    distributed.join(address, learners, index)
    from tabx_bench.train import run_train_bench  # after the group: JAX starts there

    result = run_train_bench(**options, learners=learners)
    if index == 0:
        Path(out).write_text(json.dumps(dataclasses.asdict(result)))
    distributed.leave()


if __name__ == "__main__":
    _address, _learners, _index, _share, _options, _out = sys.argv[1:]
    member(_address, int(_learners), int(_index), _share == "1", json.loads(_options), _out)

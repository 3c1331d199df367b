"""A Ray run seen from outside while it runs: its record and its level buffer.

`RUN_DIR/ray.json` (written by the Ray driver, `workers.ray.driver.RunRecord`) says whether
the run is running, where its cluster is and what its actors are called; `tabx runs status`
prints it, `tabx runs buffer` joins the cluster and asks the run's LevelService for its
buffer as it is now (the level-buffer file format, so the summary is `tabx buffer inspect`'s).
"""

from __future__ import annotations

import json
import os
from pathlib import Path
from typing import Any

from level_buffer import LevelBuffer
from tabx.errors import UserError
from ued.config import ConfigError
from workers.ray.driver import RAY_RECORD
from workers.ray.start import check_reachable


def read_record(run_dir: str | Path) -> dict[str, Any]:
    """The run's `ray.json`, or a UserError saying why there is none to read."""
    path = Path(run_dir) / RAY_RECORD
    if not Path(run_dir).is_dir():
        raise UserError(f"{run_dir}: no such run folder")
    if not path.exists():
        raise UserError(f"{path}: no Ray record: the run was not trained with --ray, or its "
                        f"actors have not started yet")
    try:
        data = json.loads(path.read_text())
    except (OSError, UnicodeDecodeError, json.JSONDecodeError, RecursionError) as err:
        raise UserError(f"{path}: not a readable Ray record ({err})") from None
    if not isinstance(data, dict) or "status" not in data:
        raise UserError(f"{path}: not a Ray record (expected an object with a 'status')")
    return data


def driver_alive(record: dict[str, Any]) -> bool:
    """Whether the driver that wrote a `running` record still runs (on this machine)."""
    pid = record.get("driver_pid")
    if record.get("status") != "running" or not isinstance(pid, int):
        return False
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


def rate_lines(record: dict[str, Any]) -> list[str]:
    """The rate line of `tabx runs status`: env steps/s that trained the policy and those
    played only to score levels, over the record's window (a record written before the split
    was kept holds one rate: the loop's steps, trained or not)."""
    window = record.get("rate_window_s")
    over = f" over the last {window:.0f} s" if window else ""
    buffer = f"; buffer: {record.get('buffer_size')}"
    trained = record.get("trained_steps_per_s")
    if isinstance(trained, int | float):
        explored = record.get("explored_steps_per_s")
        split = (f", explored {explored:,.0f}" if isinstance(explored, int | float) else
                 " (explored: not recorded)")
        return [f"env steps/s{over}: trained {trained:,.0f}{split}{buffer}"]
    rate = record.get("env_steps_per_s")
    if isinstance(rate, int | float) and rate:
        return [f"env steps/s of the loop's steps, trained or explored{over}: {rate:,.0f}"
                f"{buffer}"]
    return []


def status_text(run_dir: str | Path, record: dict[str, Any]) -> str:
    """`tabx runs status`: the run's state, actors and nodes, restarts, rate and staleness."""
    status = record["status"]
    if status == "running" and not driver_alive(record):
        status = "running (its driver is not alive on this machine: it may run elsewhere, or " \
                 "have been killed)"
    first, last = (record.get("steps") or [0, 0])[:2]
    total = record.get("total_steps")
    lines = [f"{run_dir}: {status}; {record.get('mode', '?')} schedule; step {last}"
             f"{f' of {total}' if total else ''} (this session from step {first})"]
    if record.get("error"):
        lines.append(f"stopped by: {record['error']}")
    lines.extend(rate_lines(record))
    if "trained_steps" in record:
        lines.append(f"trained env steps: {record['trained_steps']:,}, explored: "
                     f"{record.get('explored_steps', 0):,}; committed batches "
                     f"{record.get('committed_batches', 0)}, re-scored "
                     f"{record.get('rescored', 0)}, re-issued {record.get('reissued', 0)}")
    staleness = record.get("staleness") or {}
    if staleness:
        lines.append("staleness at commit (versions: batches): "
                     + ", ".join(f"{k}: {v}" for k, v in staleness.items()))
    restarts = record.get("restarts") or {}
    placement = record.get("placement") or {}
    names = record.get("actors") or {name: "" for name in placement}
    if names:
        lines.append("actors:")
        for role in names:
            node = placement.get(role, "?")
            lines.append(f"  {role:<12} node {node[:12]}  deaths {restarts.get(role, 0)}")
    if record.get("updated"):
        lines.append(f"record updated {record['updated']}")
    return "\n".join(lines)


def live_buffer(run_dir: str | Path, timeout_s: float = 60.0) -> tuple[LevelBuffer, int]:
    """The level buffer of a running Ray run, from its LevelService: (buffer, its size in
    bytes). Joins the run's cluster as a client (with Ray's token authentication)."""
    record = read_record(run_dir)
    if record["status"] != "running":
        raise UserError(f"{run_dir}: the run is {record['status']}; read its snapshots "
                        f"instead: tabx buffer inspect {Path(run_dir) / 'levels'}/buffer-N.msgpack")
    os.environ.setdefault("RAY_AUTH_MODE", "token")
    os.environ.setdefault("RAY_USAGE_STATS_ENABLED", "0")
    try:
        import ray
    except ImportError:
        raise UserError("tabx runs buffer needs Ray: pip install -e '.[ray]'") from None
    address, namespace = record.get("address"), record.get("namespace")
    service = (record.get("actors") or {}).get("service")
    if not (address and namespace and service):
        raise UserError(f"{Path(run_dir) / RAY_RECORD}: no address, namespace or service "
                        f"actor recorded")
    try:
        check_reachable(address, f"{RAY_RECORD}'s address")
    except ConfigError as err:
        raise UserError(f"{run_dir}: {err}") from None
    connected_here = not ray.is_initialized()
    if connected_here:
        ray.init(address=address, namespace=namespace, logging_level="ERROR")
    try:
        try:
            actor = ray.get_actor(service, namespace=namespace)
        except ValueError:
            raise UserError(f"{run_dir}: its LevelService ({service}) is gone: the run has "
                            f"ended or its driver died") from None
        data = ray.get(actor.buffer_bytes.remote(), timeout=timeout_s)
        if data is None:
            raise UserError(f"{run_dir}: the run's method keeps no level buffer")
        return LevelBuffer.from_bytes(data, name=f"{service} (live)"), len(data)
    finally:
        if connected_here:
            ray.shutdown()


__all__ = ["live_buffer", "read_record", "status_text"]

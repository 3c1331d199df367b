"""Nothing a command starts outlives it: a watchdog that ends the processes a command started
(a Ray of its own: GCS, raylet, agents, workers) once the command's process is gone, however it
ended (SIGKILL included).

Ray's processes share the fate of the driver that started them only in part: killed with
SIGKILL, a `tabx sweep` left Ray 2.60's DashboardAgent and RuntimeEnvAgent running, adopted by
init, every time (their check of the raylet's death ends in a report to a GCS that is gone).

    guard = ProcessGuard()
    with guard.marking():        # processes started in here carry the guard's mark
        ray.init(...)
    ...
    ray.shutdown()
    guard.close()                # the watchdog ends whatever is left, then exits

The watchdog is a process of its own session (a Ctrl-C to the command's terminal does not
reach it). While the command runs it records, every `POLL_S`, the command's descendants (a
process id and its start time, so that a reused id is never taken for one of them); it also
knows the processes that carry the guard's mark, an environment variable (`MARK`) that the
processes started in `marking()` and their descendants inherit (a process that rewrites its
title, as Ray's do, may overwrite it: hence both). At the end of file of a pipe only the
command's process holds (`close`, or the process gone) it sends SIGTERM to every recorded or
marked process still running and to their descendants, and SIGKILL after `GRACE_S` to those
left. Processes that are neither (another command's Ray) are never touched.
"""

from __future__ import annotations

import contextlib
import os
import select
import signal
import subprocess
import sys
import time
import uuid
from collections.abc import Iterator
from pathlib import Path

MARK = "TABX_PROCESS_GUARD"
GRACE_S = 5.0  # between SIGTERM and SIGKILL
POLL_S = 0.5  # between the watchdog's looks at the command's descendants

Process = tuple[int, int]  # (pid, start time in clock ticks since boot)


def process_table() -> dict[int, tuple[int, int]]:
    """Every running process (not the exited ones waiting for their parent, zombies): pid ->
    (parent pid, start time)."""
    out = {}
    for entry in Path("/proc").iterdir():
        if not entry.name.isdigit():
            continue
        try:
            stat = (entry / "stat").read_text()
        except OSError:  # gone
            continue
        fields = stat[stat.rindex(")") + 2:].split()  # after the command name, which may hold ')'
        if fields[0] not in ("Z", "X"):
            out[int(entry.name)] = (int(fields[1]), int(fields[19]))
    return out


def descendants(roots: set[int], table: dict[int, tuple[int, int]]) -> set[Process]:
    """The processes below `roots` in `table` (not the roots themselves)."""
    children: dict[int, list[int]] = {}
    for pid, (ppid, _) in table.items():
        children.setdefault(ppid, []).append(pid)
    out, todo = set(), list(roots)
    while todo:
        for child in children.get(todo.pop(), []):
            if (child, table[child][1]) not in out:
                out.add((child, table[child][1]))
                todo.append(child)
    return out


def marked(token: str) -> set[Process]:
    """Processes (other than this one) whose environment holds `MARK=token`."""
    needle = f"{MARK}={token}".encode()
    table = process_table()
    out = set()
    for pid, (_, start) in table.items():
        if pid == os.getpid():
            continue
        try:
            environ = Path(f"/proc/{pid}/environ").read_bytes()
        except OSError:  # gone, or another user's
            continue
        if needle in environ.split(b"\0"):
            out.add((pid, start))
    return out


def alive(processes: set[Process]) -> set[Process]:
    """Those of `processes` still running (the same start time: not a reused id), with the
    processes below them."""
    table = process_table()
    running = {(pid, start) for pid, start in processes if table.get(pid, (0, -1))[1] == start}
    return running | descendants({pid for pid, _ in running}, table)


def end(processes: set[Process], grace_s: float = GRACE_S) -> set[Process]:
    """SIGTERM `processes` (those still running, and their descendants), SIGKILL those left
    after `grace_s`; the processes signalled."""
    signalled: set[Process] = set()
    for sig, wait_s in ((signal.SIGTERM, grace_s), (signal.SIGKILL, 1.0)):
        targets = alive(processes | signalled)
        for pid, _ in targets:
            with contextlib.suppress(OSError):
                os.kill(pid, sig)
        signalled |= targets
        deadline = time.monotonic() + wait_s
        while targets and time.monotonic() < deadline:
            time.sleep(0.1)
            targets = alive(targets)
    return signalled


class ProcessGuard:
    """A watchdog over the processes this process starts (see the module doc)."""

    def __init__(self) -> None:
        self.token = f"{os.getpid()}-{uuid.uuid4().hex[:12]}"
        read, self._write = os.pipe()  # not inherited by what this process starts
        env = {k: v for k, v in os.environ.items() if k != MARK}
        root = str(Path(__file__).resolve().parents[1])
        env["PYTHONPATH"] = os.pathsep.join(p for p in (root, env.get("PYTHONPATH")) if p)
        try:
            self.watchdog = subprocess.Popen(
                [sys.executable, "-c", "import sys; from workers.process_guard import watch; "
                 "watch(int(sys.argv[1]), sys.argv[2])", str(os.getpid()), self.token],
                stdin=read, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
                start_new_session=True, env=env)
        finally:
            os.close(read)

    @contextlib.contextmanager
    def marking(self) -> Iterator[None]:
        """Processes started in this block carry the mark."""
        old = os.environ.get(MARK)
        os.environ[MARK] = self.token
        try:
            yield
        finally:
            if old is None:
                os.environ.pop(MARK, None)
            else:
                os.environ[MARK] = old

    def close(self, wait_s: float = 2 * GRACE_S + 5) -> None:
        """End the guarded processes still running (after an orderly shutdown: none, or Ray's
        agents on their way out), then the watchdog."""
        if self._write < 0:
            return
        os.close(self._write)
        self._write = -1
        with contextlib.suppress(subprocess.TimeoutExpired):
            self.watchdog.wait(wait_s)


def watch(guarded: int, token: str) -> None:
    """The watchdog of process `guarded`: record its descendants until the end of stdin (it
    closed the pipe, or is gone), then end them and the processes carrying `token`."""
    # Only what started after the watchdog: the command's processes from before (a test
    # session's own) are not the guard's.
    table = process_table()
    since = table[os.getpid()][1]
    guarded_start = table.get(guarded, (0, -1))[1]
    seen: set[Process] = set()
    with contextlib.suppress(OSError):
        while True:
            ready, _, _ = select.select([sys.stdin.buffer], [], [], POLL_S)
            if ready and not os.read(sys.stdin.fileno(), 4096):
                break
            table = process_table()
            if table.get(guarded, (0, -2))[1] != guarded_start:
                break  # gone (its id may already be another process's)
            seen |= descendants({guarded}, table)
    ours = {(pid, start) for pid, start in seen | marked(token)
            if start >= since and pid != os.getpid()}
    end(ours)


__all__ = ["GRACE_S", "MARK", "POLL_S", "ProcessGuard", "alive", "descendants", "end",
           "marked", "process_table", "watch"]

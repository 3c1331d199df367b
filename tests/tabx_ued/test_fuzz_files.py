"""Files that are not what a command expects, beside tests/tabx_ued/test_fuzz_inputs.py's damaged
contents: outputs that are devices, FIFOs, symlinks or folders; level-buffer inputs that are
FIFOs, devices, folders or huge sparse files; names that end in a newline; checkpoints whose
array data or level snapshot changed after they were saved; and modules that would touch a
device when imported.

Each case asserts one clear line (a non-zero exit from a command), no traceback, a time bound
(a FIFO or device never blocks a reader) and no file changed outside what the command may
write. Commands run in-process (`tabx_ued.cli.main`); one subprocess imports every module with
no usable JAX platform.
"""

from __future__ import annotations

import hashlib
import io
import json
import os
import shutil
import stat
import subprocess
import sys
import threading
import time
from pathlib import Path

import jax
import msgpack
import numpy as np
import pytest
from test_learners_helpers import tiny_config

from level_buffer import BufferFileError, LevelBuffer
from level_buffer.fileformat import MAGIC
from tabx.editor.server import EditorApp, EditorError
from tabx.files import OutputError, atomic_write_bytes
from tabx.scenarios import ScenarioError, load_file
from tabx_ued.cli import main
from ued.checkpoint import CheckpointError, Checkpoints
from ued.experiment import learner_for
from workers.resume import restore_intact

ROOT = Path(__file__).resolve().parents[2]
FAST_S = 5.0  # every refusal here is immediate; a blocked open or a whole read would not be


BIG_FILE = 1 << 20


def tree(folder: Path) -> dict[str, str]:
    """Every entry under `folder`: relative path -> kind and content (SHA-256 of a file)."""
    out = {}
    for path in sorted(folder.rglob("*")):
        rel = str(path.relative_to(folder))
        mode = os.lstat(path).st_mode
        if stat.S_ISLNK(mode):
            out[rel] = f"link -> {os.readlink(path)}"
        elif stat.S_ISREG(mode) and os.stat(path).st_size > BIG_FILE:
            # The 1 GB sparse files: hashing them whole took most of a test's time. Any write
            # moves the modification time; the head is where a reader would have written.
            info = os.stat(path)
            with open(path, "rb") as f:
                head = hashlib.sha256(f.read(BIG_FILE)).hexdigest()
            out[rel] = f"{info.st_size} bytes, mtime {info.st_mtime_ns}, head {head}"
        elif stat.S_ISREG(mode):
            out[rel] = hashlib.sha256(path.read_bytes()).hexdigest()
        else:
            out[rel] = f"mode {stat.S_IFMT(mode):o}"
    return out


def run_cli(capsys, argv: list[str]) -> tuple[int, str, str, float]:
    t0 = time.monotonic()
    try:
        code = main(argv)
    except SystemExit as exc:  # argparse
        code = exc.code
    out, err = capsys.readouterr()
    return code, out, err, time.monotonic() - t0


def assert_one_line(result, argv: list[str], *fragments: str) -> str:
    code, out, err, elapsed = result
    lines = [line for line in err.splitlines() if line.strip()]
    assert code not in (0, None), (argv, out, err)
    assert "Traceback" not in out + err, err[-3000:]
    assert len(lines) == 1 and lines[0].startswith(f"tabx {argv[0]}: error: "), err[-2000:]
    assert "(unexpected:" not in lines[0], lines[0]
    for fragment in fragments:
        assert fragment in lines[0], (fragment, lines[0])
    assert elapsed < FAST_S, (argv, elapsed)
    return lines[0]


@pytest.fixture
def buffer_file(tmp_path) -> Path:
    template = {"units": {"health": np.zeros(3, np.float32)}, "arena": np.zeros(2, np.float32)}
    buf = LevelBuffer(template, capacity=4, seed=0)
    buf.insert_batch({"units": {"health": np.ones((2, 3), np.float32)},
                      "arena": np.ones((2, 2), np.float32)}, [0.5, 0.7])
    return buf.save(tmp_path / "buffer.msgpack")


# --- outputs: written whole, through, or refused -----------------------------------------------


def test_a_symlinked_output_keeps_its_link(tmp_path, buffer_file, capsys):
    target = tmp_path / "real.json"
    target.write_text("old")
    link = tmp_path / "link.json"
    link.symlink_to(target.name)
    code, _, err, _ = run_cli(capsys, ["buffer", "export", str(buffer_file), "0",
                                       "--out", str(link)])
    assert code == 0, err
    assert link.is_symlink() and os.readlink(link) == target.name
    assert json.loads(target.read_text())  # the target holds the new file
    assert not list(tmp_path.glob(".*.tmp"))


def test_a_fifo_output_is_written_through(tmp_path, buffer_file, capsys):
    fifo = tmp_path / "out.fifo"
    os.mkfifo(fifo)
    received = []
    reader = threading.Thread(target=lambda: received.append(fifo.read_bytes()), daemon=True)
    reader.start()
    before = tree(tmp_path)
    code, _, err, elapsed = run_cli(capsys, ["buffer", "export", str(buffer_file), "0",
                                             "--out", str(fifo)])
    reader.join(FAST_S)
    assert code == 0 and elapsed < FAST_S, err
    assert received and json.loads(received[0])
    assert stat.S_ISFIFO(os.lstat(fifo).st_mode) and tree(tmp_path) == before


def test_a_device_output_is_written_through_not_replaced(tmp_path):
    """A link to /dev/null: a rename would replace the link (or, named directly and run as
    root, the device node itself); the bytes go to the device instead."""
    link = tmp_path / "null"
    link.symlink_to(os.devnull)
    atomic_write_bytes(link, b"{}\n")
    assert os.readlink(link) == os.devnull and stat.S_ISCHR(os.stat(link).st_mode)
    assert stat.S_ISCHR(os.stat(os.devnull).st_mode)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["null"]


def test_an_open_file_by_name_is_written_at_its_place(tmp_path):
    """`--json /dev/stdout > out.txt` or `/dev/fd/N`: the bytes follow what the stream holds,
    in the same file (a rename would swap the file under the shell's descriptor)."""
    read_end, write_end = os.pipe()
    try:
        for name in (f"/dev/fd/{write_end}", f"/proc/self/fd/{write_end}"):
            atomic_write_bytes(name, b"through the pipe")
            assert os.read(read_end, 100) == b"through the pipe"
    finally:
        os.close(read_end)
        os.close(write_end)
    out = tmp_path / "out.txt"
    with open(out, "wb") as stream:
        stream.write(b"table\n")
        stream.flush()
        inode = os.fstat(stream.fileno()).st_ino
        atomic_write_bytes(f"/dev/fd/{stream.fileno()}", b"{}\n")
    assert out.read_bytes() == b"table\n{}\n" and out.stat().st_ino == inode


@pytest.mark.skipif(not os.path.exists("/dev/full"), reason="no /dev/full")
def test_a_full_device_and_a_folder_are_one_line(tmp_path, buffer_file, capsys):
    full = tmp_path / "full"
    full.symlink_to("/dev/full")  # writing to /dev/full only fails: harmless
    folder = tmp_path / "folder"
    folder.mkdir()
    before = tree(tmp_path)
    for out, fragment in ((full, "No space left on device"), (folder, "it is a directory")):
        argv = ["buffer", "export", str(buffer_file), "0", "--out", str(out)]
        assert_one_line(run_cli(capsys, argv), argv, f"cannot write {out}", fragment)
        assert tree(tmp_path) == before
    with pytest.raises(OutputError, match="a directory"):
        atomic_write_bytes(folder, b"x")


# --- level-buffer inputs: refused before they are read -----------------------------------------


def sparse_with_header(path: Path, valid: bytes, payload_bytes: int) -> None:
    """A file whose outer map is a real buffer's header followed by a `payload_bytes` payload
    that is a hole: the size it declares is its size."""
    outer = msgpack.unpackb(valid, raw=False)
    head = b"\x85" + b"".join(msgpack.packb(x, use_bin_type=True) for x in (
        "magic", MAGIC, "format_version", 1, "header", outer["header"], "sha256", "0" * 64,
        "payload"))
    head += b"\xc6" + payload_bytes.to_bytes(4, "big")
    with open(path, "wb") as f:
        f.write(head)
        f.truncate(len(head) + payload_bytes)


def test_buffer_inputs_that_are_not_buffer_files_are_refused_unread(tmp_path, buffer_file,
                                                                    capsys):
    fifo = tmp_path / "levels.fifo"
    os.mkfifo(fifo)  # no writer: opening it to read would block
    folder = tmp_path / "folder.msgpack"
    folder.mkdir()
    zeros = tmp_path / "zeros.msgpack"
    with open(zeros, "wb") as f:
        f.truncate(1 << 30)  # 1 GB of hole
    declared = tmp_path / "declared.msgpack"
    sparse_with_header(declared, buffer_file.read_bytes(), (1 << 30) - 1)
    cases = {fifo: "a FIFO", folder: "a directory", zeros: "not a readable level-buffer file",
             declared: "more than a buffer of capacity 4 holds"}
    before = tree(tmp_path)
    for path, fragment in cases.items():
        argv = ["buffer", "inspect", str(path)]
        done: list = []
        worker = threading.Thread(target=lambda a=argv, d=done: d.append(run_cli(capsys, a)),
                                  daemon=True)
        worker.start()
        worker.join(FAST_S)
        if worker.is_alive() and path == fifo:  # let the blocked reader go before failing
            os.close(os.open(fifo, os.O_WRONLY | os.O_NONBLOCK))
        assert done, f"{argv} blocked"
        assert_one_line(done[0], argv, str(path), fragment)
        with pytest.raises(BufferFileError, match=fragment):
            LevelBuffer.load(path)
    assert tree(tmp_path) == before


# --- names ending in a newline -----------------------------------------------------------------


def test_a_scenario_name_ending_in_a_newline_is_refused(tmp_path, capsys, monkeypatch):
    data = json.loads((ROOT / "tabx/data/scenarios/challenges/crossfire.json").read_text())
    path = tmp_path / "crossfire2.json"
    path.write_text(json.dumps({**data, "name": "crossfire2\n"}))
    with pytest.raises(ScenarioError, match="name"):
        load_file(path)
    argv = ["scenarios", "validate", str(path)]
    assert_one_line(run_cli(capsys, argv), argv, "name")
    user = tmp_path / "user-scenarios"
    monkeypatch.setenv("TABX_SCENARIO_DIR", str(user))
    with pytest.raises(EditorError) as info:
        EditorApp().save({"scenario": {**data, "category": "user"}, "name": "ok3\n",
                          "category": "user"})
    assert info.value.status == 400 and info.value.path == "name"
    assert not user.exists() or not any(user.rglob("*"))


# --- checkpoints: digests of arrays and of the level snapshot ----------------------------------


@pytest.fixture(scope="module")
def tiny_state():
    return learner_for(tiny_config()).init(jax.random.key(0))


def array_files(step_dir: Path) -> list[Path]:
    return sorted((p for p in step_dir.rglob("*") if p.is_file() and p.parent.name == "d"),
                  key=lambda p: -p.stat().st_size)


def same_arrays(a, b) -> bool:
    return all(np.array_equal(np.asarray(x), np.asarray(y))
               for x, y in zip(jax.tree.leaves(a), jax.tree.leaves(b), strict=True))


def test_a_flipped_bit_in_array_data_is_never_restored_silently(tmp_path, tiny_state):
    """Orbax has no checksum of the values: a flip in an array's bytes used to restore as a
    changed weight. Now each flip is refused naming the checkpoint, or it restored the same
    arrays (it hit bytes no array is read from)."""
    with Checkpoints(tmp_path / "checkpoints") as checkpoints:
        checkpoints.save(1, tiny_state, jax.random.key(1))
    data_file = array_files(tmp_path / "checkpoints" / "1")[0]
    valid = data_file.read_bytes()
    caught = checked = 0
    # Orbax compresses most arrays: a flip in a chunk's framing fails to decode ("cannot be
    # restored"); one in the values decodes to other values, which only the digests catch.
    for at in np.linspace(0.02, 0.6, 12):
        if caught and checked >= 4:
            break
        checked += 1
        pos = int(len(valid) * at)
        data_file.write_bytes(valid[:pos] + bytes([valid[pos] ^ 0x04]) + valid[pos + 1:])
        with Checkpoints(tmp_path / "checkpoints", create=False) as checkpoints:
            try:
                state, _, _ = checkpoints.restore(tiny_state, 1)
            except CheckpointError as err:
                assert str(err).startswith(f"{tmp_path / 'checkpoints' / '1'}: "), err
                assert "\n" not in str(err)
                caught += "damaged: array train_state/" in str(err)
            else:
                assert same_arrays(state, tiny_state), f"a flip at {pos} restored changed"
    data_file.write_bytes(valid)
    assert caught, "no flip reached the digests"


def test_a_damaged_checkpoint_or_edited_snapshot_falls_back(tmp_path, tiny_state):
    """Step 2's array data flipped, then step 2's state file edited plausibly: each time
    resume says so in one line and continues from step 1, setting step 2 aside."""
    run = tmp_path / "run"
    levels = run / "levels"
    levels.mkdir(parents=True)
    covers = ["levels/state-{}.json"]
    with Checkpoints(run / "checkpoints", covers=covers) as checkpoints:
        for step in (1, 2):
            state = {"curriculum": {"method": "dr"}, "version": step}
            (levels / f"state-{step}.json").write_text(json.dumps(state))
            checkpoints.save(step, tiny_state, jax.random.key(step))
    pristine = tmp_path / "pristine"
    os.rename(run, pristine)

    def flip_array(r: Path) -> None:
        path = array_files(r / "checkpoints" / "2")[0]
        data = bytearray(path.read_bytes())
        data[len(data) // 10] ^= 0x04
        path.write_bytes(bytes(data))

    def edit_state(r: Path) -> None:  # still a valid state file
        (r / "levels" / "state-2.json").write_text(json.dumps({"curriculum": {"method": "dr"},
                                                              "version": 3}))

    for harm, fragment in (
            (flip_array, f"{run / 'checkpoints' / '2'}: cannot be restored"),
            (edit_state, f"{run / 'levels' / 'state-2.json'}: changed after checkpoint 2 was "
                         f"saved")):
        shutil.copytree(pristine, run)
        harm(run)
        out = io.StringIO()
        with Checkpoints(run / "checkpoints", covers=covers) as checkpoints:
            restored = restore_intact(run, checkpoints, tiny_state, snapshots=True,
                                      needs_buffer=False, stream=out)
        assert restored is not None and restored[2] == 1
        lines = out.getvalue().splitlines()
        assert lines[0].startswith(f"resume: step 2 is damaged: {fragment}"), lines
        assert lines[1].startswith("resume: from step 1; ") and len(lines) == 2, lines
        assert not (run / "checkpoints" / "2").exists()
        assert not (run / "levels" / "state-2.json").exists()
        shutil.rmtree(run)
    # A policy needs only the parameters: an edited state file does not stop `tabx eval`.
    edit_state(pristine)
    with Checkpoints(pristine / "checkpoints", covers=covers) as checkpoints:
        params, step = checkpoints.restore_params(tiny_state.params, 2)
        assert step == 2 and same_arrays(params, tiny_state.params)
        assert checkpoints.metadata(2) == {}  # the digests are not the caller's metadata


# --- nothing touches a device at import --------------------------------------------------------

# JaxMARL builds arrays when imported; the adapters that import it inherit that.
IMPORTS_JAXMARL = ("tabx.compat.jaxmarl", "tabx_bench.peers.smax")
IMPORT_ALL = f"""
import importlib, pkgutil, resource, sys
failed = []
for package in ("tabx", "tabx_bench", "level_buffer", "ued", "workers", "tabx_ued"):
    names = [package] + [m.name for m in pkgutil.walk_packages(
        importlib.import_module(package).__path__, package + ".", onerror=failed.append)]
    for name in names:
        if name.endswith(".__main__") or name in {IMPORTS_JAXMARL!r}:
            continue
        try:
            importlib.import_module(name)
        except Exception as err:
            failed.append(f"{{name}}: {{type(err).__name__}}: {{err}}"[:300])
print("\\n".join(failed) or "imported")
# /dev/zero as a buffer file, with the address space bounded should it be read after all.
size = int(open("/proc/self/statm").read().split()[0]) * resource.getpagesize()
resource.setrlimit(resource.RLIMIT_AS, (size + (512 << 20), resource.RLIM_INFINITY))
from tabx_ued.cli import main
sys.exit(main(["buffer", "inspect", "/dev/zero"]))
"""


def test_no_module_touches_a_device_at_import():
    """With a JAX platform that cannot start (as `JAX_PLATFORMS=cuda` on a host without a
    GPU), every module imports: none builds an array when imported."""
    env = {**os.environ, "JAX_PLATFORMS": "nodevice", "PYTHONPATH": str(ROOT)}
    proc = subprocess.run([sys.executable, "-c", IMPORT_ALL], env=env, capture_output=True,
                          text=True, timeout=120, cwd=ROOT)
    assert proc.stdout.strip() == "imported", proc.stdout[-3000:] + proc.stderr[-3000:]
    lines = [line for line in proc.stderr.splitlines() if line.strip()]
    assert proc.returncode == 2 and len(lines) == 1, proc.stderr[-3000:]
    assert lines[0].startswith("tabx buffer: error: /dev/zero: cannot read: a character device")


@pytest.mark.skipif(shutil.which("nvidia-smi") is not None, reason="a GPU may be here")
def test_an_unusable_jax_platform_is_one_line_naming_it():
    """`JAX_PLATFORMS=cuda tabx rollout crossfire` without a GPU: one line naming the setting
    and the platforms this machine has (JAX raises a bare AssertionError there)."""
    env = {**os.environ, "JAX_PLATFORMS": "cuda", "PYTHONPATH": str(ROOT)}
    proc = subprocess.run([sys.executable, "-m", "tabx_ued.cli", "rollout", "crossfire"],
                          env=env, capture_output=True, text=True, timeout=240, cwd=ROOT)
    lines = [line for line in proc.stderr.splitlines() if line.strip()]
    assert proc.returncode == 2 and len(lines) == 1, proc.stderr[-3000:]
    assert lines[0].startswith("tabx rollout: error: JAX_PLATFORMS=cuda: JAX cannot start"), lines
    assert "this machine has: cpu" in lines[0] and "unexpected" not in lines[0], lines

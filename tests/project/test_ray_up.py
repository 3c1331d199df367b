"""`ray up` / `ray exec` / `ray submit` / `ray down` with cluster-local.yaml on this machine: a
head on 127.0.0.1 and a worker node on 127.0.0.2, reached over ssh. Opt-in (slow) and only where
this machine has what the launcher needs: an ssh server that lets the current user in on
127.0.0.1 and 127.0.0.2 with ~/.ssh/id_ed25519 and no password, and rsync
(docs/distributed_operations.md, "A cluster with ray up", says how to set that up).

The launcher file is cluster-local.yaml with its placeholders filled for the loopback addresses
and its setup command left out: both nodes are this machine, where the project is installed
already (the file's own setup would re-point that install to ~/tabx-ued).
"""

from __future__ import annotations

import getpass
import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest
import yaml

ROOT = Path(__file__).resolve().parents[2]
KEY = Path.home() / ".ssh" / "id_ed25519"

pytestmark = pytest.mark.slow


def ssh_ok(host: str) -> bool:
    if not KEY.is_file() or shutil.which("ssh") is None:
        return False
    done = subprocess.run(["ssh", "-i", str(KEY), "-o", "BatchMode=yes", "-o",
                           "StrictHostKeyChecking=accept-new", "-o", "ConnectTimeout=5", host,
                           "true"], capture_output=True, timeout=30)
    return done.returncode == 0


@pytest.fixture(scope="module")
def launcher(tmp_path_factory):
    missing = [what for what, ok in (("rsync", shutil.which("rsync") is not None),
                                     ("ssh to 127.0.0.1", ssh_ok("127.0.0.1")),
                                     ("ssh to 127.0.0.2", ssh_ok("127.0.0.2"))) if not ok]
    if missing:
        pytest.skip(f"the launcher needs {', '.join(missing)} on this machine")
    spec = yaml.safe_load((ROOT / "cluster-local.yaml").read_text())
    spec["cluster_name"] = "tabx-ued-loopback-test"
    spec["provider"].update(head_ip="127.0.0.1", worker_ips=["127.0.0.2"])
    spec["auth"]["ssh_user"] = getpass.getuser()
    spec["max_workers"] = 1
    spec["file_mounts"] = {"~/tabx-ued": str(ROOT),
                           "~/.ray/auth_token": str(Path.home() / ".ray" / "auth_token")}
    spec["setup_commands"] = []
    spec["worker_start_ray_commands"] = [
        "RAY_AUTH_MODE=token ray start --address=$RAY_HEAD_IP:6379 "
        "--node-ip-address=127.0.0.2 --disable-usage-stats"]
    token = Path.home() / ".ray" / "auth_token"
    if not token.is_file():
        pytest.skip("no ~/.ray/auth_token (start a head once with `ray start --head`)")
    path = tmp_path_factory.mktemp("rayup") / "cluster-loopback.yaml"
    path.write_text(yaml.safe_dump(spec))
    env = {**os.environ, "RAY_ENABLE_WINDOWS_OR_OSX_CLUSTER": "0"}
    up = subprocess.run(["ray", "up", "-y", str(path)], capture_output=True, text=True,
                        timeout=600, env=env)
    assert up.returncode == 0, up.stdout[-3000:] + up.stderr[-3000:]
    yield path, env
    subprocess.run(["ray", "down", "-y", str(path)], capture_output=True, timeout=300, env=env)


def test_ray_up_runs_a_training_run_on_both_nodes_and_ray_down_stops_it(launcher, tmp_path):
    path, env = launcher
    run_dir = tmp_path / "run"
    command = (f"cd ~/tabx-ued && RAY_AUTH_MODE=token {sys.executable} -m tabx_ued train "
               f"configs/ued/quickstart.yaml --ray --address auto ray.explorers=2 "
               f"'ued.eval_suites=[]' --run-dir {run_dir} --max-updates 3")
    done = subprocess.run(["ray", "exec", str(path), command], capture_output=True, text=True,
                          timeout=600, env=env)
    assert done.returncode == 0, done.stdout[-3000:] + done.stderr[-3000:]
    record = json.loads((run_dir / "ray.json").read_text())
    assert record["status"] == "finished" and record["steps"][1] == 3
    assert len(set(record["placement"].values())) == 2  # the Explorers spread over both nodes

    script = tmp_path / "status.py"
    script.write_text("import sys\nfrom tabx_ued.cli import main\n"
                      "sys.exit(main(['runs', 'status', sys.argv[1]]))\n")
    submitted = subprocess.run(["ray", "submit", str(path), str(script), str(run_dir)],
                               capture_output=True, text=True, timeout=300, env=env)
    assert submitted.returncode == 0, submitted.stdout[-3000:] + submitted.stderr[-3000:]
    assert f"{run_dir}: finished" in submitted.stdout

"""Continuous scoring on a two-node Ray cluster on 127.0.0.1 (ray.cluster_utils.Cluster)."""
import json

import ray
from ray.cluster_utils import Cluster

from tabx_bench.ued import format_table, run_ued_bench
from ued.config import load_config

cluster = Cluster(initialize_head=True, head_node_args={
    "num_cpus": 2, "include_dashboard": False, "object_store_memory": 256 * 2**20})
try:
    cluster.add_node(num_cpus=2, object_store_memory=256 * 2**20)
    cluster.wait_for_nodes(timeout=120)
    ray.init(address=cluster.address, logging_level="ERROR")
    print("nodes", len([n for n in ray.nodes() if n["Alive"]]), flush=True)
    config = load_config("ued/quickstart", ["ued.eval_suites=[]", "ray.schedule=continuous",
                                            f"ray.address={cluster.address}"])
    results = run_ued_bench(config, [0, 1, 2], 4, 16, local=False)
    print(format_table(results))
    with open("/tmp/explore33_cluster.jsonl", "w") as f:
        for r in results:
            f.write(json.dumps(r.to_json()) + "\n")
finally:
    ray.shutdown()
    cluster.shutdown()

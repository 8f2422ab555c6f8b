"""Shared fixtures.  ``GARMENTGNN_NO_SCATTER=1`` hides torch-scatter so the
suite exercises PyG's native-scatter path even where torch-scatter is installed."""
import os
import sys

if os.environ.get("GARMENTGNN_NO_SCATTER") == "1":
    sys.modules["torch_scatter"] = None  # makes `import torch_scatter` raise ImportError
# the bench reports of the tests leave out the held-out animation (seconds each);
# tests/test_bench_page.py turns it on
os.environ.setdefault("GARMENTGNN_BENCH_MEDIA", "0")

import pytest  # noqa: E402
import torch  # noqa: E402

from garmentgnn.geometry import edge_features, faces_to_edge_index, grid_mesh  # noqa: E402


def random_graph(num_nodes: int, num_edges: int, seed: int = 0, sort: bool = False):
    """A random directed graph in which every node has at least one incoming edge."""
    g = torch.Generator().manual_seed(seed)
    src = torch.randint(0, num_nodes, (num_edges,), generator=g)
    dst = torch.randint(0, num_nodes, (num_edges,), generator=g)
    src = torch.cat([src, torch.roll(torch.arange(num_nodes), 1)])
    dst = torch.cat([dst, torch.arange(num_nodes)])
    ei = torch.stack([src, dst])
    if sort:  # CSR order of adj_t: by (target, source), duplicates removed
        key = torch.unique(ei[1] * num_nodes + ei[0])
        ei = torch.stack([key % num_nodes, key // num_nodes])
    else:
        ei = ei[:, torch.randperm(ei.size(1), generator=g)]
    return ei


@pytest.fixture
def mesh_graph():
    """A small garment-like sheet: positions, faces, sorted edge_index, edge features."""
    pos, faces = grid_mesh(7, 6)
    pos = pos + 0.02 * torch.randn(pos.shape, generator=torch.Generator().manual_seed(1))
    ei = faces_to_edge_index(faces, pos.size(0))
    return pos, faces, ei, edge_features(pos, ei)


def skirt_dataset(out, motions, num_frames, held_out=None, name="t"):
    """A generated dataset in ``out`` (returned): the mini skirt (200 vertices) on the
    regular capsule body in silk, one ``num_frames``-frame sequence per motion name of
    ``motions``, :func:`garmentgnn.sim.stand_in.skinned_wobble` as the simulation;
    ``held_out``: split -> the motion names it holds out."""
    # the generator and the simulator are heavy imports: only the tests that make a
    # dataset pay for them
    from garmentgnn.data import Spec, generate, motion_key  # noqa: PLC0415 (see above)
    from garmentgnn.sim.stand_in import skinned_wobble  # noqa: PLC0415 (see above)
    g = [{"kind": "skirt", "params": {"length": "mini"}, "resolution": 200}]
    b = [{"model": "capsule", "shape": "regular"}]
    m = [{"name": n, "num_frames": num_frames, "speed": 1.0, "amplitude": 1.0} for n in motions]
    held = {split: {"motions": [motion_key(x) for x in m if x["name"] in names]}
            for split, names in (held_out or {}).items()}
    s = generate(Spec(name, g, b, m, ["silk"], held_out=held), out, workers=0,
                 simulate_fn=skinned_wobble, progress=False)
    assert s.done == len(motions) and s.failed == 0
    return out


def numbers(obj):
    """Every int/float (not bool) inside nested dicts and lists."""
    if isinstance(obj, dict):
        for v in obj.values():
            yield from numbers(v)
    elif isinstance(obj, list):
        for v in obj:
            yield from numbers(v)
    elif isinstance(obj, (int, float)) and not isinstance(obj, bool):
        yield obj


#: below this a UV area counts as zero: (1 um)^2, a millionth of the ``sliver_face``
#: stability case's 1.7e-6 m^2 on the tiny preset (a collapsed face gives 0, or ~1e-20
#: where a BLAS code path rounds differently)
ZERO_AREA_M2 = 1e-12


def tiny_stand_in(out):
    """The ``tiny`` dataset preset generated in ``out`` (returned) with
    :func:`garmentgnn.sim.stand_in.skinned_wobble` as its simulation: its sequences,
    splits and held-out groups in seconds."""
    from garmentgnn.data import generate, preset  # noqa: PLC0415 (see skirt_dataset)
    from garmentgnn.sim.stand_in import skinned_wobble  # noqa: PLC0415
    s = generate(preset("tiny"), out, workers=0, simulate_fn=skinned_wobble, progress=False)
    assert s.failed == 0
    return out


def ray_head(cpus: int = 2):
    """A ``ray start --head --block`` cluster of ``cpus`` CPUs on this host, as a
    generator for a module fixture: yields its ``HOST:PORT`` once it answers, stops it
    after.  A cluster per test module: starting one takes seconds here, joining one
    a fraction of a second."""
    import socket  # noqa: PLC0415 (only the Ray tests start a cluster)
    import subprocess  # noqa: PLC0415
    import time  # noqa: PLC0415
    from pathlib import Path  # noqa: PLC0415
    os.environ.setdefault("RAY_AUTH_MODE", "disabled")
    os.environ.setdefault("RAY_USAGE_STATS_ENABLED", "0")
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        port = sock.getsockname()[1]
    exe = Path(sys.executable).with_name("ray")
    head = subprocess.Popen([str(exe), "start", "--head", f"--port={port}", f"--num-cpus={cpus}",
                             "--num-gpus=0", "--include-dashboard=false",
                             "--disable-usage-stats", "--block", "--node-ip-address=127.0.0.1"],
                            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    try:
        for _ in range(120):  # the head takes a few seconds to come up
            try:
                socket.create_connection(("127.0.0.1", port), timeout=1).close()
                break
            except OSError:
                time.sleep(0.5)
        yield f"127.0.0.1:{port}"
    finally:
        head.terminate()
        try:
            head.wait(timeout=30)
        except subprocess.TimeoutExpired:
            head.kill()

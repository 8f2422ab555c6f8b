"""``garmentgnn bench --backend ray``: each learned (method, seed) run a Ray task on a
real cluster (one ``ray start --head`` of 2 CPUs for the module), its record and
checkpoints sent back to the driver.

Oracle: the local bench with the same preset, dataset and seeds -- the tiny preset's
dataset, its simulation a test double (:func:`garmentgnn.sim.stand_in.skinned_wobble`)
so that it takes seconds.  Training for a fixed number of epochs on the CPU with one
thread and the same seed is deterministic, so the Ray runs' metrics equal the local
ones exactly.  The bad-input tests need no cluster."""
import dataclasses
import json
import os
import socket
import sys
from pathlib import Path

import pytest
import yaml

from garmentgnn.bench import methods, presets, runner
from garmentgnn.bench.dataset import prepare_dataset
from garmentgnn.bench.ray_backend import RayBackend, local_dataset, pack, unpack
from garmentgnn.cli import main as cli_main
from garmentgnn.training.recipes import recipe_path

from conftest import ray_head, tiny_stand_in

METHODS = (methods.DA, methods.FULL)


@pytest.fixture(scope="module")
def data(tmp_path_factory):
    return tiny_stand_in(tmp_path_factory.mktemp("tiny"))


@pytest.fixture(scope="module")
def address():
    pytest.importorskip("ray", reason="Ray is an optional extra (make install installs it)")
    yield from ray_head(cpus=2)


def learned_only(*names) -> presets.Preset:
    p = presets.preset("tiny").learned_only()
    return dataclasses.replace(p, learned=dataclasses.replace(
        p.learned, methods=tuple(names), stability_cases=()))


def learned_records(out: Path):
    return {(r["method"], r["seed"]): r for r in
            (json.loads(f.read_text()) for f in sorted((out / "records").glob("learned--*")))}


@pytest.mark.slow  # two benches of 4 runs each, and a rerun: about 2 min on 2 cores
def test_ray_bench_equals_the_local_bench_and_resumes(data, address, tmp_path):
    p = learned_only(*METHODS)
    local = runner.run(p, tmp_path / "local", seeds=2, data=data, progress=False)
    on_ray = runner.run(p, tmp_path / "ray", seeds=2, data=data, progress=False,
                        backend=RayBackend(address=address))
    assert (local.ran, on_ray.ran, on_ray.failed) == (4, 4, 0)
    a, b = learned_records(tmp_path / "local"), learned_records(tmp_path / "ray")
    assert sorted(a) == sorted(b) == sorted((m, s) for m in METHODS for s in (0, 1))
    for key in a:
        assert b[key]["status"] == "ok"
        assert b[key]["metrics"] == a[key]["metrics"], key
        assert b[key]["per_sequence"] == a[key]["per_sequence"], key
        assert b[key]["steps"] == a[key]["steps"]
        # the checkpoint came back: a readable link in the driver's folder
        ckpt = Path(b[key]["checkpoint"])
        assert ckpt.parent.parent == tmp_path / "ray" / "models" and ckpt.is_symlink()
        assert ckpt.resolve().stat().st_size > 1000
        assert b[key]["dataset"]["root"] == str(data)
    assert (tmp_path / "ray" / "report.md").exists()
    assert json.loads((tmp_path / "ray" / "results.json").read_text())["records"]

    # a rerun trains nothing: every record and checkpoint kept as it was, and no cluster
    # is joined (nothing answers at this address: joining would fail)
    def stamps():
        return {f: (f.read_bytes(), f.lstat().st_mtime_ns)
                for f in sorted((tmp_path / "ray").glob("*/**/*")) if f.is_file()}
    before = stamps()
    again = runner.run(p, tmp_path / "ray", seeds=2, data=data, progress=False,
                       backend=RayBackend(address=f"127.0.0.1:{_free_port()}"))
    assert (again.ran, again.skipped) == (0, 4)
    after = stamps()
    assert {f: v for f, v in after.items() if "records" in f.parts or "models" in f.parts} \
        == {f: v for f, v in before.items() if "records" in f.parts or "models" in f.parts}


@pytest.mark.slow  # two attempts of a failing run beside a good one: about 1 min
def test_a_failing_run_is_retried_once_and_reported(data, address, tmp_path):
    doc = yaml.safe_load(recipe_path("baselines/da").read_text())
    doc["model"]["init_args"]["lr"] = -1.0  # the optimizer refuses it
    bad = tmp_path / "bad_lr.yaml"
    bad.write_text(yaml.safe_dump(doc))
    s = runner.run(learned_only(methods.DA, str(bad)), tmp_path / "out", seeds=1, data=data,
                   progress=False, backend=RayBackend(address=address))
    recs = learned_records(tmp_path / "out")
    assert (s.ran, s.failed) == (2, 1)
    assert recs[(methods.DA, 0)]["status"] == "ok"
    failed = recs[(str(bad), 0)]
    assert failed["status"] == "failed"
    assert failed["message"].startswith("failed 2 times on Ray: ")
    assert "learning rate" in failed["message"].lower()


def test_pack_and_unpack_keep_files_and_links(tmp_path):
    src = tmp_path / "a"
    (src / "sub").mkdir(parents=True)
    (src / "sub" / "x.bin").write_bytes(bytes(range(256)))
    (src / "y.txt").write_text("y")
    os.symlink("sub/x.bin", src / "last")
    files = pack(src)
    assert files == {"sub/x.bin": bytes(range(256)), "y.txt": b"y",
                     "last": {"link": "sub/x.bin"}}
    unpack(files, tmp_path / "b")
    assert (tmp_path / "b" / "last").read_bytes() == bytes(range(256))
    assert os.readlink(tmp_path / "b" / "last") == "sub/x.bin"
    assert (tmp_path / "b" / "y.txt").read_text() == "y"
    assert pack(tmp_path / "b") == files
    assert pack(tmp_path / "none") == {}


def test_a_node_without_the_dataset_unpacks_the_shipped_copy(data, tmp_path, monkeypatch):
    info = prepare_dataset(data)
    monkeypatch.setattr("tempfile.tempdir", str(tmp_path / "node"))
    elsewhere = dataclasses.replace(info, root=tmp_path / "absent")
    here = local_dataset(elsewhere, pack(data))
    assert here.root != data and str(here.root).startswith(str(tmp_path / "node"))
    assert here.fingerprint == info.fingerprint and here.content_sha256 == info.content_sha256
    with pytest.raises(RuntimeError, match="--ship-data"):
        local_dataset(dataclasses.replace(info, root=tmp_path / "absent",
                                          fingerprint="0" * 40), None)
    assert local_dataset(info, None).root == data  # at its own path: used where it is


# --------------------------------------------------------------------------- bad input
def _free_port() -> int:
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        return sock.getsockname()[1]


def _one_error(capsys, argv, *expected):
    assert cli_main(argv) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("error: "), err
    for text in expected:
        assert text in err[0]


BENCH = ["bench", "--preset", "tiny", "--learned-only", "--no-progress"]


def test_unreachable_address_is_one_error_line_and_writes_nothing(capsys, tmp_path):
    pytest.importorskip("ray")
    port = _free_port()
    out = tmp_path / "out"
    _one_error(capsys, BENCH + ["--out", str(out), "--backend", "ray", "--address",
                                f"127.0.0.1:{port}"],
               f"--address 127.0.0.1:{port}: no Ray cluster answers there",
               f"ray start --head --port={port}")
    _one_error(capsys, BENCH + ["--out", str(out), "--backend", "ray", "--address",
                                "headnode"], "expected HOST:PORT")
    assert not out.exists()


def test_backend_ray_without_ray_installed(capsys, tmp_path, monkeypatch):
    monkeypatch.setitem(sys.modules, "ray", None)  # `import ray` raises ImportError
    out = tmp_path / "out"
    _one_error(capsys, BENCH + ["--out", str(out), "--backend", "ray"],
               "--backend ray needs Ray", "pip install 'garmentgnn[ray]'")
    assert not out.exists()


def test_ray_flags_need_the_ray_backend(capsys, tmp_path):
    out = tmp_path / "out"
    _one_error(capsys, BENCH + ["--out", str(out), "--workers", "2"], "--workers",
               "add --backend ray")
    _one_error(capsys, BENCH + ["--out", str(out), "--backend", "ray", "--shard", "0/2"],
               "--shard")
    _one_error(capsys, BENCH + ["--out", str(out), "--backend", "ray", "--gpus", "-1"],
               "--gpus")
    _one_error(capsys, BENCH + ["--out", str(out), "--backend", "ray", "--workers", "2",
                                "--address", "127.0.0.1:6379"], "--workers", "--address")
    assert not out.exists()

"""Dataset generation: spec/split, atomic writes + resume (with a simulator test double),
manifest rebuild, PC2/OBJ export, the lazy PyG dataset, the CLI, and one real run."""
import importlib.util
import os
import pickle
import shutil
import struct
import subprocess
import sys
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
import torch
import trimesh

from garmentgnn.body.factory import build_body
from garmentgnn.cli import main
from garmentgnn.data import (Spec, SpecMismatch, body_key,
                             garment_key, generate, motion_key, preset, read_manifest,
                             rebuild_manifest)
from garmentgnn.data import store
from garmentgnn.data.store import LRUCache
from garmentgnn.garments import FLARES, SLEEVES, TEMPLATES
from garmentgnn.garments.templates import SKIRT_LENGTHS
from garmentgnn.garments.skinning import transfer_skinning_weights
from garmentgnn.models.inputs import GarmentInputs, with_frames
from garmentgnn.data import SequenceChunks

ROOT = Path(__file__).resolve().parents[1]
HAS_SIM = importlib.util.find_spec("garmentgnn.sim") is not None and \
    (ROOT / "src/garmentgnn/sim/__init__.py").exists()


# --------------------------------------------------------------------------- test double
def fake_simulate(garment, body, motion, material, settings=None, progress=None):
    """Deterministic stand-in for garmentgnn.sim.simulate: rest garment carried by the
    root translation plus a small seed-free wobble.  Logs each completed call to
    $GG_CALLS; with $GG_CRASH_AFTER=k it dies on call k+1 (KeyboardInterrupt in the
    main process, a hard os._exit in a worker)."""
    log = os.environ.get("GG_CALLS")
    crash = os.environ.get("GG_CRASH_AFTER")
    key = f"{garment.name}|{body_key_of(body)}|{float(motion.rotations.abs().sum()):.6f}"
    if crash is not None and log and Path(log).exists() and \
            len(Path(log).read_text().splitlines()) >= int(crash):
        if __import__("multiprocessing").parent_process() is None:
            raise KeyboardInterrupt("simulated kill")
        os._exit(3)
    if os.environ.get("GG_FAIL_KIND") == garment.kind:
        return SimpleNamespace(positions=None, ok=False, message="diverged (test double)")
    T = motion.num_frames
    t = torch.arange(T, dtype=torch.float32).view(T, 1, 1)
    P = garment.vertices[None] + motion.translation[:, None].float() \
        + 0.001 * torch.sin(t + garment.vertices[None, :, :1] * 10)
    if log:
        with open(log, "a") as f:
            f.write(key + "\n")
    return SimpleNamespace(positions=P, converged=torch.ones(T, dtype=torch.bool),
                           newton_iterations=torch.full((T,), 2), residual=torch.zeros(T),
                           ok=True, message="", seconds=0.0)


def body_key_of(body):
    return "none" if body.shape is None else ",".join(f"{x:.4f}" for x in body.shape.tolist())


def calls(path):
    p = Path(path)
    return p.read_text().splitlines() if p.exists() else []


def files_of(out):
    return {p.name: p.read_bytes() for p in sorted((Path(out) / "sequences").glob("*.npz"))}


@pytest.fixture(scope="module")
def clean_run(tmp_path_factory):
    """The tiny preset generated in-process with the test double."""
    out = tmp_path_factory.mktemp("clean")
    s = generate(preset("tiny"), out, workers=0, simulate_fn=fake_simulate, progress=False)
    assert s.done == 8 and s.failed == 0
    return out


# --------------------------------------------------------------------------- spec
def test_spec_is_deterministic_and_split_rule():
    a, b = preset("tiny").items(), preset("tiny").items()
    assert a == b and len(a) == 8
    assert len({it["id"] for it in a}) == 8
    c = preset("tiny", seed=1).items()
    assert {it["id"] for it in a}.isdisjoint({it["id"] for it in c})
    assert [it["seed"] for it in a] != [it["seed"] for it in c]
    for it in a:  # tiny holds out the arm_swing motion for test
        assert it["split"] == ("test" if it["motion"]["name"] == "arm_swing" else "train")

    g = [{"kind": k, "params": {}, "resolution": 300} for k in ("skirt", "dress")]
    bodies = [{"model": "capsule", "shape": s} for s in ("thin", "fat")]
    m = [{"name": n, "num_frames": 4, "speed": 1.0, "amplitude": 1.0} for n in ("walk", "run")]
    spec = Spec("t", g, bodies, m, ["silk"],
                held_out={"test": {"garments": [garment_key(g[1])]},
                          "val": {"bodies": [body_key(bodies[1])],
                                  "motions": [motion_key(m[1])]}})
    for it in spec.items():
        test = it["garment"]["kind"] == "dress"
        val = it["body"]["shape"] == "fat" or it["motion"]["name"] == "run"
        assert it["split"] == ("test" if test else "val" if val else "train")
    # an item's id/seed does not depend on the rest of the grid
    one = Spec("t", g[:1], bodies[:1], m[:1], ["silk"]).items()[0]
    assert one["id"] == spec.items()[0]["id"] and one["seed"] == spec.items()[0]["seed"]
    # seeded sampling
    sub = Spec("t", g, bodies, m, ["silk"], seed=3, sample=3).items()
    assert len(sub) == 3 and sub == Spec("t", g, bodies, m, ["silk"], seed=3, sample=3).items()


def test_presets_build():
    small, paper = preset("small").items(), preset("paper").items()
    assert {it["split"] for it in small} == {"train", "val", "test"}
    assert len(preset("paper").garments) >= 45 and len(paper) > 1000
    assert {it["split"] for it in paper} == {"train", "val", "test"}
    with pytest.raises(ValueError):
        preset("huge")


def test_learn_preset_has_its_stated_counts_and_held_out_groups():
    """``learn``: at least 400 sequences of 60 frames of ~400-vertex garments of every kind,
    24+ bodies, 16+ motions with speed/amplitude variants and mixes, held-out garments,
    bodies and motions; docs/dataset.md's preset table states the spec's own counts."""
    spec = preset("learn", engine="blender")
    items = spec.items()
    assert spec.engine == "blender" and len(items) == spec.sample >= 400
    assert len(spec.bodies) >= 24 and len(spec.motions) >= 16
    assert {m["num_frames"] for m in spec.motions} == {60}
    assert {(m["speed"], m["amplitude"]) for m in spec.motions} > {(1.0, 1.0)}
    assert any("+" in m["name"] for m in spec.motions)
    assert {g["kind"] for g in spec.garments} == set(TEMPLATES)
    assert {g["resolution"] for g in spec.garments} == {400}
    # every sleeve of the tops and every skirt length / flare, by the templates' own lists
    def used(kind, key):
        return {g["params"].get(key) for g in spec.garments if g["kind"] == kind}

    assert used("tshirt", "sleeves") == set(SLEEVES)
    assert used("skirt", "length") == used("dress", "length") == set(SKIRT_LENGTHS)
    assert used("skirt", "flare") >= set(FLARES) - {"straight"}  # straight = pencil
    keys = {"garments": [garment_key(g) for g in spec.garments],
            "bodies": [body_key(b) for b in spec.bodies],
            "motions": [motion_key(m) for m in spec.motions]}
    split_of = {it["id"]: it["split"] for it in items}
    for split in ("test", "val"):
        for part, held in spec.held_out[split].items():
            assert held and set(held) <= set(keys[part]), (split, part)
    item_keys = {it["id"]: {garment_key(it["garment"]), body_key(it["body"]),
                            motion_key(it["motion"])} for it in items}
    held_any = {k for h in spec.held_out.values() for v in h.values() for k in v}
    assert all(not (item_keys[i] & held_any) for i, s in split_of.items() if s == "train")
    counts = {s: sum(v == s for v in split_of.values()) for s in ("train", "val", "test")}
    assert min(counts.values()) > 0
    row = next(line for line in (ROOT / "docs" / "dataset.md").read_text().splitlines()
               if line.startswith("| `learn` |"))
    grid = len(spec.garments) * len(spec.bodies) * len(spec.motions) * len(spec.materials)
    for stated in (f"{len(spec.bodies)} anny shapes", f"{len(spec.garments)} garments",
                   f"{len(spec.motions)} x 60 frames",
                   f"seeded sample of {len(items)} of {grid:,}: {counts['train']} train, "
                   f"{counts['val']} val, {counts['test']} test"):
        assert stated in row, stated


def test_learn_long_holds_out_what_learn_holds_out_over_300_frames():
    """``learn_long``: 300-frame sequences whose held-out garments, bodies and motions are
    ``learn``'s test ones (the motion at 300 frames: the same generator, speed and
    amplitude), so a model trained on ``learn`` meets them as held out."""
    spec, learn = preset("learn_long", engine="blender"), preset("learn", engine="blender")
    items = spec.items()
    assert {m["num_frames"] for m in spec.motions} == {300}
    test = [it for it in items if it["split"] == "test"]
    assert len(test) >= 10 and {it["split"] for it in items} <= {"train", "test"}
    held = learn.held_out["test"]
    for it in test:
        m = dict(it["motion"], num_frames=60)
        for part, key in (("garment", garment_key(it["garment"])),
                          ("body", body_key(it["body"])), ("motion", motion_key(m))):
            assert (part in it["held_out"]) == (key in held[part + "s" if part != "body"
                                                             else "bodies"]), (it["id"], part)
    assert {len(it["held_out"]) > 1 for it in test} == {True, False}  # single and several
    learn_parts = ({garment_key(g) for g in learn.garments}, {body_key(b) for b in learn.bodies},
                   {motion_key(dict(m, num_frames=60)) for m in learn.motions})
    for it in items:  # every part is one of learn's
        m = dict(it["motion"], num_frames=60)
        assert garment_key(it["garment"]) in learn_parts[0] and body_key(it["body"]) in \
            learn_parts[1] and motion_key(m) in learn_parts[2]


# --------------------------------------------------------------------------- generation
def test_generate_writes_files_and_manifest(clean_run):
    man = read_manifest(clean_run)
    assert man["counts"] == {"ok": 8} and len(man["items"]) == 8
    assert man["code"]["version"]
    for rec in man["items"]:
        assert rec["status"] == "ok" and rec["seconds"] is not None
        p = clean_run / rec["file"]
        assert store.validate_sequence(p, rec["id"]) is None
        seq = store.load_sequence(p)
        assert seq["positions"].dtype == np.float32
        assert seq["positions"].shape == (8, rec["num_vertices"], 3)
        assert seq["meta"]["split"] == rec["split"] and seq["meta"]["seed"] == rec["seed"]
        assert seq["meta"]["settings"] == {"fps": 30.0, "substeps": 4, "preroll_frames": 6}
    assert not list(Path(clean_run).rglob(".*tmp*"))  # no temporaries left


@pytest.mark.slow
def test_deterministic_and_parallel_equal(clean_run, tmp_path):
    out = tmp_path / "par"
    s = generate(preset("tiny"), out, workers=2, simulate_fn=fake_simulate, progress=False)
    assert s.done == 8
    assert files_of(out) == files_of(clean_run)  # byte-identical, 2 spawn workers


def test_resume_after_kill_in_process(clean_run, tmp_path, monkeypatch):
    out, log = tmp_path / "run", tmp_path / "calls.txt"
    monkeypatch.setenv("GG_CALLS", str(log))
    monkeypatch.setenv("GG_CRASH_AFTER", "3")
    with pytest.raises(KeyboardInterrupt):
        generate(preset("tiny"), out, workers=0, simulate_fn=fake_simulate, progress=False)
    man = read_manifest(out)
    assert man["counts"] == {"ok": 3, "pending": 5} and len(files_of(out)) == 3
    monkeypatch.delenv("GG_CRASH_AFTER")
    s = generate(preset("tiny"), out, workers=0, simulate_fn=fake_simulate, progress=False)
    assert (s.done, s.skipped, s.failed) == (5, 3, 0)
    c = calls(log)
    assert len(c) == 8 and len(set(c)) == 8  # every item simulated exactly once
    assert files_of(out) == files_of(clean_run)
    s = generate(preset("tiny"), out, workers=0, simulate_fn=fake_simulate, progress=False)
    assert (s.done, s.skipped) == (0, 8) and len(calls(log)) == 8


@pytest.mark.slow
def test_resume_after_worker_death(clean_run, tmp_path, monkeypatch):
    out, log = tmp_path / "run", tmp_path / "calls.txt"
    monkeypatch.setenv("GG_CALLS", str(log))
    monkeypatch.setenv("GG_CRASH_AFTER", "2")
    with pytest.raises(RuntimeError, match="worker process died"):
        generate(preset("tiny"), out, workers=1, simulate_fn=fake_simulate, progress=False)
    first = calls(log)
    done = {r["id"] for r in read_manifest(out)["items"] if r["status"] == "ok"}
    assert len(first) == 2 and len(done) == 2
    monkeypatch.delenv("GG_CRASH_AFTER")
    s = generate(preset("tiny"), out, workers=0, simulate_fn=fake_simulate, progress=False)
    assert (s.done, s.skipped) == (6, 2)
    c = calls(log)
    assert len(c) == 8 and len(set(c)) == 8
    assert files_of(out) == files_of(clean_run)


def test_corrupt_file_is_redone_and_limit(clean_run, tmp_path, monkeypatch):
    out, log = tmp_path / "run", tmp_path / "calls.txt"
    monkeypatch.setenv("GG_CALLS", str(log))
    s = generate(preset("tiny"), out, workers=0, simulate_fn=fake_simulate, progress=False,
                 limit=2)
    assert (s.done, s.pending) == (2, 6)
    victim = sorted((out / "sequences").glob("*.npz"))[0]
    victim.write_bytes(victim.read_bytes()[:100])  # a truncated file
    s = generate(preset("tiny"), out, workers=0, simulate_fn=fake_simulate, progress=False,
                 log=lambda m: None)
    assert (s.done, s.skipped) == (7, 1) and len(calls(log)) == 9
    assert files_of(out) == files_of(clean_run)


def test_failed_items_are_recorded_not_written(tmp_path, monkeypatch):
    monkeypatch.setenv("GG_FAIL_KIND", "tshirt")
    out = tmp_path / "run"
    s = generate(preset("tiny"), out, workers=0, simulate_fn=fake_simulate, progress=False)
    assert (s.done, s.failed) == (4, 4)
    recs = read_manifest(out)["items"]
    for r in recs:
        if r["garment"]["kind"] == "tshirt":
            assert r["status"] == "failed" and "diverged (test double)" in r["message"]
            assert not (out / "sequences" / f"{r['id']}.npz").exists()
    s = generate(preset("tiny"), out, workers=0, simulate_fn=fake_simulate, progress=False)
    assert (s.done, s.failed, s.skipped) == (0, 4, 8)  # failed kept unless retry_failed
    monkeypatch.delenv("GG_FAIL_KIND")
    s = generate(preset("tiny"), out, workers=0, simulate_fn=fake_simulate, progress=False,
                 retry_failed=True)
    assert (s.done, s.failed) == (4, 0)


def test_spec_mismatch_refused(clean_run):
    with pytest.raises(SpecMismatch):
        generate(preset("tiny", seed=5), clean_run, workers=0, simulate_fn=fake_simulate,
                 progress=False)


def test_manifest_rebuild(clean_run, tmp_path):
    out = tmp_path / "copy"
    shutil.copytree(clean_run, out)
    before = read_manifest(out)
    (out / "manifest.json").unlink()
    after = rebuild_manifest(out)
    key = ("id", "status", "split", "seed", "garment", "body", "motion", "material",
           "num_frames", "num_vertices", "file")
    assert [{k: r[k] for k in key} for r in after["items"]] == \
        [{k: r[k] for k in key} for r in before["items"]]
    # without spec.json: listed from the sequence files alone
    (out / "spec.json").unlink()
    assert sorted(r["id"] for r in rebuild_manifest(out)["items"]) == \
        sorted(r["id"] for r in before["items"])


# --------------------------------------------------------------------------- export
def read_pc2(path):
    data = Path(path).read_bytes()
    sig, ver, n, start, rate, samples = struct.unpack("<12siiffi", data[:32])
    assert sig == b"POINTCACHE2\0" and ver == 1
    flat = struct.unpack(f"<{samples * n * 3}f", data[32:])
    return np.array(flat, dtype=np.float32).reshape(samples, n, 3), start, rate


def test_pc2_and_obj_export(clean_run, tmp_path):
    seq_path = sorted((clean_run / "sequences").glob("*.npz"))[0]
    seq = store.load_sequence(seq_path)
    assert main(["export", "--seq", str(seq_path), "--format", "pc2",
                 "--out", str(tmp_path / "a.pc2"), "--start-frame", "1"]) == 0
    P, start, rate = read_pc2(tmp_path / "a.pc2")
    assert start == 1.0 and rate == 1.0
    np.testing.assert_array_equal(P, seq["positions"])
    assert main(["export", "--seq", str(seq_path), "--format", "obj",
                 "--out", str(tmp_path / "objs")]) == 0
    objs = sorted((tmp_path / "objs").glob("*.obj"))
    assert len(objs) == seq["positions"].shape[0]
    m = trimesh.load(objs[3], process=False)
    np.testing.assert_allclose(m.vertices, seq["positions"][3], atol=1e-5)
    np.testing.assert_array_equal(m.faces, seq["garment_faces"])


# --------------------------------------------------------------------------- dataset
def test_skinning_weights_are_stored_and_read_back(clean_run, tmp_path):
    """Each file holds the weights the engine skinned its garment with (oracle: the same
    transfer recomputed), and the model inputs read them from the file."""
    rec = read_manifest(clean_run)["items"][0]
    seq = store.load_sequence(store.sequence_path(clean_run, rec))
    body = build_body(seq["meta"]["body"])
    W = transfer_skinning_weights(torch.from_numpy(seq["garment_vertices"]).float(),
                                  torch.from_numpy(seq["garment_faces"]).long(),
                                  body.vertices.float(), body.weights.float())
    np.testing.assert_allclose(seq["garment_skin_weights"], W.numpy(), rtol=0, atol=1e-6)
    # an edited copy: the inputs follow the file, not a recomputation
    copy = tmp_path / "copy"
    shutil.copytree(clean_run, copy)
    arrays = {k: v for k, v in seq.items() if k != "meta" and isinstance(v, np.ndarray)}
    arrays["garment_skin_weights"] = np.roll(arrays["garment_skin_weights"], 1, axis=1)
    store.write_sequence(store.sequence_path(copy, rec), arrays, seq["meta"])
    store.rebuild_manifest(copy)
    ds = SequenceChunks(copy, split=rec["split"], chunk=1, ids=[rec["id"]])
    np.testing.assert_array_equal(ds[0].skin_weights.numpy(), arrays["garment_skin_weights"])


def test_sequence_chunks_items_and_lazy_loading(clean_run):
    """The model inputs read from the files: poses, history, simulated garment and the
    posed body of each frame, loaded lazily (the index comes from the manifest alone)."""
    ds = SequenceChunks(clean_run, split="train", chunk=1, history=2, cache_size=1)
    assert ds.num_file_loads == 0
    assert len(ds) == 4 * 8  # 4 train sequences x 8 frames
    d0 = ds[0]
    assert ds.num_file_loads == 1 and isinstance(d0, GarmentInputs)
    seq = store.load_sequence(clean_run / ds.records[0]["file"])
    V = seq["garment_vertices"].shape[0]
    P = torch.from_numpy(seq["positions"])
    R = torch.from_numpy(seq["motion_rotations"])
    assert d0.num_nodes == V and d0.gt.shape == (1, V, 3) and torch.equal(d0.gt[0], P[0])
    d3 = ds[3]
    assert ds.num_file_loads == 1  # same sequence: cached
    assert int(d3.frames[0]) == 3 and d3.seq_id == ds.records[0]["id"]
    assert torch.equal(d3.gt[0], P[3])
    assert d3.rotations.shape == (1, 3, R.shape[1], 3)
    assert torch.equal(d3.rotations[0], R[1:4])  # frames t-2 .. t
    assert torch.equal(ds[1].rotations[0], R[[0, 0, 1]])  # frame 0 repeated before the start
    ei = d3.edge_index
    assert (ei[1, 1:] >= ei[1, :-1]).all()
    assert d3.faces.shape[1] == 3 and d3.face_uv.shape == (d3.faces.shape[0], 3, 2)
    # the posed body, recomputed from the body model + the stored motion
    body = build_body(seq["meta"]["body"])
    bv, _ = body.pose(R[3:4], torch.from_numpy(seq["motion_translation"][3:4]))
    torch.testing.assert_close(d3.body_pos, bv.float())
    # kept by chunk: a second visit returns the same posed body, not a recomputation
    first = ds[3].body_pos
    assert ds[3].body_pos.data_ptr() == first.data_ptr()
    torch.testing.assert_close(first, bv.float())
    with pytest.raises(ValueError, match="`body_pos`"):
        with_frames(ds.static(0), body, R, torch.from_numpy(seq["motion_translation"]),
                    torch.arange(3, 5), 2, body_pos=d3.body_pos)
    ds[8]  # next sequence evicts the first (cache_size=1)
    ds[0]
    assert ds.num_file_loads == 3
    # the default bounds keep both; a byte bound below one sequence keeps only the newest
    roomy = SequenceChunks(clean_run, split="train", chunk=1, history=2)
    tight = SequenceChunks(clean_run, split="train", chunk=1, history=2, cache_bytes=1)
    for d in (roomy, tight):
        for i in (0, 8, 0, 8):
            d[i]
    assert roomy.num_file_loads == 2 and tight.num_file_loads == 4
    with pytest.raises(ValueError, match="`cache_bytes`"):
        SequenceChunks(clean_run, split="train", cache_bytes=-1)
    assert len(SequenceChunks(clean_run, split="test", chunk=1)) == 4 * 8
    with pytest.raises(ValueError, match="no 'val' split; name one that its manifest lists"):
        SequenceChunks(clean_run, split="val")  # tiny holds out no val split


def _env():
    env = dict(os.environ)
    env["PYTHONPATH"] = os.pathsep.join([str(ROOT / "tests"), str(ROOT / "src"),
                                         env.get("PYTHONPATH", "")])
    return env


def test_cli_help():
    r = subprocess.run([sys.executable, "-m", "garmentgnn.cli", "generate", "--help"],
                       capture_output=True, text=True, env=_env(), timeout=120)
    assert r.returncode == 0 and "--preset" in r.stdout and "--limit" in r.stdout
    for argv in (["--help"], ["export", "--help"], ["manifest", "--help"]):
        with pytest.raises(SystemExit) as e:
            main(argv)
        assert e.value.code == 0


def test_cli_generate_with_double(tmp_path, monkeypatch, capsys):
    cmd = [sys.executable, "-m", "garmentgnn.cli", "generate", "--preset", "tiny", "--out",
           str(tmp_path), "--workers", "0", "--no-estimate", "--no-progress",
           "--simulate-fn", "test_data:fake_simulate", "--limit", "3"]
    r = subprocess.run(cmd, capture_output=True, text=True, env=_env(), timeout=120)
    assert r.returncode == 0, r.stderr
    assert "3 simulated" in r.stdout and "5 pending" in r.stdout
    monkeypatch.setenv("GG_FAIL_KIND", "tshirt")
    assert main(cmd[3:-2]) == 1  # in-process: 5 more items, the 4 tshirts fail
    out = capsys.readouterr().out
    assert "FAILED" in out and "3 skipped" in out


def _real_tiny(tmp_path, *extra):
    cmd = [sys.executable, "-m", "garmentgnn.cli", "generate", "--preset", "tiny", "--out",
           str(tmp_path), "--workers", "2", "--no-progress", *extra]
    return subprocess.run(cmd, capture_output=True, text=True, env=_env(), timeout=1800)


@pytest.mark.slow
@pytest.mark.skipif(not HAS_SIM, reason="garmentgnn.sim not available yet")
def test_cli_generate_tiny_real_simulator(tmp_path):
    """The real simulator through the CLI on 2 items of ``tiny`` (minutes on 2 cores).
    Checks the pipeline, not the simulator: every item is ok (valid file) or failed with
    a message, and the exit status says which."""
    r = _real_tiny(tmp_path, "--limit", "2")
    print(r.stdout, r.stderr[-2000:])
    assert "estimate:" in r.stdout
    man = read_manifest(tmp_path)
    done = [x for x in man["items"] if x["status"] != "pending"]
    assert len(done) == 2
    fails = [x for x in done if x["status"] == "failed"]
    assert r.returncode == (1 if fails else 0), r.stderr[-2000:]
    for x in done:
        if x["status"] == "ok":
            assert store.validate_sequence(tmp_path / x["file"], x["id"]) is None
        else:
            assert x["message"] and not (tmp_path / "sequences" / f"{x['id']}.npz").exists()
    oks = [x for x in done if x["status"] == "ok"]
    if oks:
        ds = SequenceChunks(tmp_path, split=None, chunk=1)
        assert len(ds) == 8 * len(oks) and torch.isfinite(ds[len(ds) - 1].gt).all()
    # rerun: nothing simulated again
    r2 = _real_tiny(tmp_path, "--limit", "0", "--no-estimate")
    assert "0 simulated, 2 skipped" in r2.stdout, r2.stdout + r2.stderr[-2000:]


def test_lru_cache_bounds_the_bytes_of_its_arrays():
    """With ``max_bytes`` the cache evicts the least recently used entries until its
    arrays (numpy and torch, in nested dicts) fit, and always keeps the newest one."""
    c = LRUCache(100, max_bytes=1000)
    def item(n):
        return {"a": np.zeros(n, np.float32), "b": [torch.zeros(n, dtype=torch.float64)]}

    for k in "abc":  # 12 * 25 = 300 bytes each
        c.get_or_build(k, lambda: item(25))
    assert list(c) == ["a", "b", "c"] and c.bytes == 900
    c.get_or_build("a", lambda: item(0))  # a hit: "a" becomes the most recent
    c.get_or_build("d", lambda: item(25))  # 1,200 bytes: the least recent ("b") goes
    assert list(c) == ["c", "a", "d"] and c.bytes == 900
    c.get_or_build("e", lambda: item(200))  # 2,400 bytes alone: kept, everything else goes
    assert list(c) == ["e"] and c.bytes == 2400
    c2 = pickle.loads(pickle.dumps(c))
    assert c2.max_bytes == 1000 and len(c2) == 0 and c2.bytes == 0


def test_lru_cache_bound_and_pickles_empty():
    c = LRUCache(2)
    built = []
    for k in (1, 2, 1, 3):  # 1 is used again, so 2 is the least recent when 3 arrives
        c.get_or_build(k, lambda k=k: built.append(k) or k * 10)
    assert list(c) == [1, 3] and built == [1, 2, 3]
    c2 = pickle.loads(pickle.dumps(c))  # DataLoader/DDP workers get a fresh, empty cache
    assert isinstance(c2, LRUCache) and c2.capacity == 2 and len(c2) == 0

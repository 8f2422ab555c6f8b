"""Bad or odd input is never silent: each test feeds one input a careless or hostile user
would give (contact, units, motion files, checkpoints, dataset folders, jobs, settings,
OBJ encodings, the CLI) and checks the correct result or a clear error."""
import json
import logging
import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
import torch
import trimesh

import garmentgnn
from garmentgnn.body import CapsuleBodyModel
from garmentgnn.body.body import Body
from garmentgnn.body.skeleton import Skeleton
from garmentgnn.cli import main as cli_main
from garmentgnn.data import Spec, SpecMismatch, generate, preset, read_manifest
from garmentgnn.data import store
from garmentgnn.data.export import write_obj_sequence
from garmentgnn.data.worker import run_item
from garmentgnn.garments import load_garment, make_garment
from garmentgnn.garments.garment import Garment
from garmentgnn.geometry import grid_mesh, penetration_depth, signed_distance
from garmentgnn.motion import load_bvh, make_motion, save_bvh
from garmentgnn.motion.sequence import Motion, match_joints
from garmentgnn.physics import material
from garmentgnn.sim import SimSettings, simulate
from garmentgnn.training import GarTransModule
from garmentgnn.data import SequenceChunks
from garmentgnn.training.integrity import CheckpointError, load_checkpoint_file
from garmentgnn.models import GarTrans

from test_data import fake_simulate
from test_training import NY, root  # noqa: F401  (module-scoped toy dataset)

ROOT = Path(__file__).resolve().parents[1]
CONFIG = str(ROOT / "src" / "garmentgnn" / "recipes" / "gartrans.yaml")


def env():
    e = dict(os.environ)
    e["PYTHONPATH"] = os.pathsep.join([str(ROOT / "tests"), str(ROOT / "src"),
                                       e.get("PYTHONPATH", "")])
    return e


def one_joint_body(mesh: trimesh.Trimesh) -> Body:
    v = torch.tensor(mesh.vertices, dtype=torch.float32)
    return Body(v, torch.tensor(mesh.faces), Skeleton(["root"], torch.tensor([-1])),
                torch.zeros(1, 3), torch.ones(len(v), 1))


def still(T):
    return Motion(torch.zeros(T, 1, 3), torch.zeros(T, 3), ["root"], 30.0)


def patch(size=0.04, at=(0.0, 0.0, 0.13), n=4):
    pos, faces = grid_mesh(n, n, (size, size), dtype=torch.float32)
    uv = pos[:, :2].clone()
    return Garment(pos + torch.tensor(at) - torch.tensor([size / 2, size / 2, 0.0]), faces, uv)


# ------------------------------------------------------------------ contact truth
def two_spheres():
    """A big sphere with a small one poking out of its top: closed, overlapping pieces
    (like the capsule body's limbs in its torso)."""
    a = trimesh.creation.icosphere(subdivisions=3, radius=0.3)
    b = trimesh.creation.icosphere(subdivisions=3, radius=0.1)
    b.apply_translation([0, 0, 0.25])
    return a, b, trimesh.util.concatenate([a, b])


def test_cloth_inside_the_body_is_flagged_not_ok():
    """Cloth 170 mm inside the big sphere but 20 mm from the small one's surface: the
    candidate search's sign (relative to the small sphere) says 'outside'; the exact
    end-of-frame check flags every frame."""
    a, b, m = two_spheres()
    body = one_joint_body(m)
    g = patch()
    res = simulate(g, body, still(4), material("silk"), SimSettings(substeps=2))
    old = signed_distance(res.positions.double(), body.vertices.double(), body.faces,
                          candidates=8).distance
    assert float(old.min()) > 0  # what the contact check saw: all outside
    assert res.ok and "exact penetration" in res.message
    assert bool(res.penetrating.all())
    # oracle: every vertex is inside sphere a (all its face planes), and the depth is
    # at most the distance to a's surface
    X = res.positions[-1].double().numpy()
    assert (((X[:, None] - a.triangles[None, :, 0]) * a.face_normals[None]).sum(-1) < 0).all()
    depth_a = 0.3 - res.positions[-1].double().norm(dim=-1)
    assert float(res.penetration[-1]) <= float(depth_a.max()) + 1e-3
    assert float(res.penetration[-1]) > 0.01


def test_penetration_depth_matches_trimesh():
    ico = trimesh.creation.icosphere(subdivisions=3, radius=0.2)
    pts = torch.from_numpy(np.random.default_rng(0).uniform(-0.3, 0.3, (200, 3)))
    d = penetration_depth(pts, torch.from_numpy(ico.vertices), torch.from_numpy(ico.faces))
    P = pts.numpy()
    # oracle: trimesh's closest point on every triangle; inside = behind every face plane
    # (a convex mesh)
    n, F = len(P), len(ico.faces)
    q = trimesh.triangles.closest_point(np.tile(ico.triangles, (n, 1, 1)), np.repeat(P, F, 0))
    dist = np.linalg.norm(np.repeat(P, F, 0) - q, axis=1).reshape(n, F).min(1)
    inside = (((P[:, None] - ico.triangles[None, :, 0]) * ico.face_normals[None]).sum(-1)
              < 0).all(1)
    assert 20 < inside.sum() < 180
    assert np.allclose(d.numpy(), np.where(inside, dist, 0.0), atol=1e-9)


def pen_simulate(garment, body, motion, material, settings=None, progress=None):
    """A simulator double whose frame 1 is 36 mm inside the body."""
    T = motion.num_frames
    pen = torch.zeros(T)
    pen[1] = 0.036
    return SimpleNamespace(positions=garment.vertices[None].expand(T, -1, -1).clone(),
                           converged=torch.ones(T, dtype=torch.bool), ok=True, message="",
                           penetration=pen, max_penetration=0.01)


def test_penetrating_frames_reach_the_manifest(tmp_path):
    item = preset("tiny").items()[0]
    rec = run_item(item, str(tmp_path), simulate_fn=pen_simulate)
    assert rec["status"] == "ok" and rec["penetrating_frames"] == 1
    assert rec["max_penetration_depth"] == pytest.approx(0.036)
    seq = store.load_sequence(store.sequence_path(tmp_path, rec))
    assert seq["penetration"][1] == pytest.approx(0.036)
    doc = store.rebuild_manifest(tmp_path)
    assert doc["items"][0]["penetrating_frames"] == 1


# ------------------------------------------------------------------ units / placement
def test_garment_in_millimetres_or_far_away_is_refused():
    a, b, m = two_spheres()
    body = one_joint_body(a)
    g = patch(size=0.3, at=(0, 0, 0.31))
    mm = Garment(g.vertices * 1000, g.faces, g.uv * 1000)
    with pytest.raises(ValueError, match=r"garment.vertices.*millimetres.*0\.001"):
        simulate(mm, body, still(2), material("silk"))
    far = Garment(g.vertices + torch.tensor([10.0, 0, 0]), g.faces, g.uv)
    with pytest.raises(ValueError, match=r"garment.vertices.*away from the body.*translate"):
        simulate(far, body, still(2), material("silk"))
    with pytest.raises(ValueError, match="millimetres"):  # also without a body
        simulate(mm, None, still(2), material("silk"))


# ------------------------------------------------------------------ BVH joint order
def test_bvh_roundtrip_is_matched_by_name():
    model = CapsuleBodyModel()
    body = model()
    motion = make_motion("walk", model.skeleton, num_frames=5, fps=30.0, seed=0,
                         rest_joints=body.joints.double())
    text = save_bvh(None, motion, model.skeleton, body.joints)
    _, back = load_bvh(text, up="Y")
    assert back.joint_names != list(model.skeleton.joint_names)  # depth-first order
    rot = match_joints(back, model.skeleton.joint_names)
    v0, _ = body.pose(motion.rotations, motion.translation)
    v1, _ = body.pose(rot, back.translation)
    assert float((v0 - v1).norm(dim=-1).max()) < 1e-4  # metres: the same pose
    v_count, _ = body.pose(back.rotations, back.translation)  # matched by count only
    assert float((v0 - v_count).norm(dim=-1).max()) > 0.1
    bad = Motion(back.rotations, back.translation,
                 ["Pelvis"] + back.joint_names[1:], back.fps)
    with pytest.raises(ValueError, match=r"unknown: \[.Pelvis.\].*missing.*retarget"):
        match_joints(bad, model.skeleton.joint_names)
    g = Garment(body.vertices[:50].clone(), torch.tensor([[0, 1, 2]]), torch.zeros(50, 2))
    with pytest.raises(ValueError, match="unknown"):
        simulate(g, body, bad, material("silk"))


# ------------------------------------------------------------------ checkpoints
def small_module():
    return GarTransModule(GarTrans(num_joints=3, num_body_vertices=10, nystrom_dim=NY, heads=2))


def write_ckpt(path, module):
    ck = {"state_dict": module.state_dict(), "hyper_parameters": dict(module.hparams),
          "epoch": 0, "global_step": 0, "pytorch-lightning_version": "2.6.0"}
    module.on_save_checkpoint(ck)
    torch.save(ck, path)
    return ck


def test_checkpoint_with_a_flipped_bit_is_refused(tmp_path):
    m = small_module()
    p = tmp_path / "m.ckpt"
    write_ckpt(p, m)
    assert GarTransModule.load_from_checkpoint(p) is not None  # intact: loads
    data = bytearray(p.read_bytes())
    w = max(m.state_dict().values(), key=lambda t: t.numel())
    at = bytes(data).find(w.detach().numpy().tobytes()[:64])
    assert at > 0
    data[at + 5] ^= 0x10  # one bit of one weight
    bad = tmp_path / "bad.ckpt"
    bad.write_bytes(bytes(data))
    with pytest.raises(CheckpointError, match="integrity digest"):
        GarTransModule.load_from_checkpoint(bad)
    with pytest.raises(CheckpointError, match="integrity digest"):
        load_checkpoint_file(bad)
    (tmp_path / "cut.ckpt").write_bytes(bytes(data[: len(data) // 2]))
    with pytest.raises(CheckpointError, match="unreadable checkpoint"):
        load_checkpoint_file(tmp_path / "cut.ckpt")


def test_flag_conflicting_with_checkpoint_is_an_error(tmp_path, capsys):
    p = tmp_path / "sat.ckpt"
    write_ckpt(p, small_module())  # dynamic_layer="sat"
    rc = cli_main(["train", "fit", "--config", CONFIG, "--data.root", str(tmp_path),
                   "--model.model.dynamic_layer", "gat", "--ckpt_path", str(p)])
    err = capsys.readouterr().err.strip().splitlines()
    assert rc == 2 and len(err) == 1
    assert "--model.model.dynamic_layer 'gat' (checkpoint: 'sat')" in err[0]


# ------------------------------------------------------------------ dataset folders
def test_generate_refuses_to_clobber_and_empty_paths(tmp_path, capsys):
    other = tmp_path / "other"
    spec = Spec("x", preset("tiny").garments[:1], preset("tiny").bodies[:1],
                preset("tiny").motions[:1], ["silk"], seed=7)
    generate(spec, other, workers=0, simulate_fn=fake_simulate, progress=False)
    (other / store.SPEC).unlink()  # only the other dataset's manifest.json is left
    before = (other / store.MANIFEST).read_bytes()
    with pytest.raises(SpecMismatch, match="--force"):
        generate(preset("tiny"), other, workers=0, simulate_fn=fake_simulate, progress=False)
    assert (other / store.MANIFEST).read_bytes() == before
    cmd = ["generate", "--out", str(other), "--workers", "0", "--no-estimate",
           "--no-progress", "--simulate-fn", "test_data:fake_simulate", "--limit", "1"]
    assert cli_main(cmd) == 2 and "--force" in capsys.readouterr().err
    assert cli_main(cmd + ["--force"]) == 0
    assert read_manifest(other)["name"] == "tiny"
    with pytest.raises(SystemExit) as e:
        cli_main(["generate", "--out", ""])
    assert e.value.code == 2 and "empty path" in capsys.readouterr().err
    with pytest.raises(ValueError, match="`out`: empty path"):
        generate(preset("tiny"), "", workers=0, simulate_fn=fake_simulate, progress=False)
    assert cli_main(["manifest", "--out", str(tmp_path / "typo")]) == 2
    assert "no such folder" in capsys.readouterr().err


def test_changed_sequence_file_is_an_integrity_error(root):  # noqa: F811
    rec = read_manifest(root)["items"][0]
    path = store.sequence_path(root, rec)
    good = path.read_bytes()
    try:
        data = bytearray(good)
        data[len(data) // 2] ^= 0x01
        path.write_bytes(bytes(data))
        with pytest.raises(store.IntegrityError, match="SHA-256"):
            SequenceChunks(root, split=None, chunk=4, history=2, nystrom_dim=NY,
                           num_landmarks=16)[0]
    finally:
        path.write_bytes(good)


# ------------------------------------------------------------------ jobs
def sleepy_simulate(garment, body, motion, material, settings=None, progress=None):
    """Writes this worker's pid to $GG_PIDS, then simulates for a long time."""
    with open(os.environ["GG_PIDS"], "a") as f:
        f.write(f"{os.getpid()}\n")
    time.sleep(120)
    raise RuntimeError("unreachable in the test")


def alive(pid):
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    stat = Path(f"/proc/{pid}/stat")
    return not (stat.exists() and stat.read_text().split(")")[-1].split()[0] == "Z")


@pytest.mark.slow
def test_workers_die_when_generate_is_killed(tmp_path):
    pids = tmp_path / "pids"
    e = env()
    e["GG_PIDS"] = str(pids)
    proc = subprocess.Popen([sys.executable, "-m", "garmentgnn.cli", "generate", "--out",
                             str(tmp_path / "out"), "--workers", "1", "--no-estimate",
                             "--no-progress", "--simulate-fn",
                             "test_bad_input:sleepy_simulate"], env=e,
                            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    try:
        t0 = time.time()
        while not (pids.exists() and pids.read_text().strip()) and time.time() - t0 < 60:
            time.sleep(0.2)
        worker = int(pids.read_text().split()[0])
        assert alive(worker)
        proc.send_signal(signal.SIGKILL)
        proc.wait(10)
        t0 = time.time()
        while alive(worker) and time.time() - t0 < 10:
            time.sleep(0.1)
        assert not alive(worker), "the worker outlived its SIGKILLed parent"
    finally:
        if proc.poll() is None:
            proc.kill()
        for line in pids.read_text().split() if pids.exists() else []:
            if alive(int(line)):
                os.kill(int(line), signal.SIGKILL)


# ------------------------------------------------------------------ settings / subcommands
@pytest.mark.parametrize("kw,name", [
    ({"max_refinements": -1}, "max_refinements"), ({"line_search_steps": 0}, "line_search_steps"),
    ({"max_penetration": float("nan")}, "max_penetration"), ({"tol": 0.0}, "tol"),
    ({"distance_candidates": 0}, "distance_candidates"), ({"gravity": (0, 0)}, "gravity"),
    ({"contact_radius": -1.0}, "contact_radius"), ({"substeps": 2.5}, "substeps")])
def test_sim_settings_validated_at_construction(kw, name):
    with pytest.raises(ValueError, match=f"settings.{name}"):
        SimSettings(**kw)


@pytest.mark.slow  # a one-step fit, then test and predict (~45 s)
def test_train_test_prints_lbs_beside_the_method_and_predict_writes(root, tmp_path,  # noqa: F811
                                                                     capsys):
    args = ["--config", CONFIG, "--data.root", str(root), "--data.chunk", "4",
            "--data.history", "2", "--data.nystrom_dim", str(NY), "--data.num_landmarks",
            "16", "--data.test_split", "val", "--trainer.limit_test_batches", "1",
            "--trainer.enable_progress_bar", "false", "--trainer.default_root_dir",
            str(tmp_path), "--trainer.logger.init_args.save_dir", str(tmp_path),
            "--model.compile_search", "false"]
    assert cli_main(["train", "fit"] + args + ["--trainer.max_epochs", "1",
                                               "--trainer.limit_train_batches", "1",
                                               "--trainer.limit_val_batches", "1"]) == 0
    (last,) = tmp_path.rglob("last.ckpt")  # test and predict score a trained checkpoint
    args += ["--ckpt_path", str(last)]
    capsys.readouterr()
    assert cli_main(["train", "test"] + args) == 0
    out = capsys.readouterr().out
    assert "test/" in out and "| GarTrans (sat) |" in out and "| LBS only |" in out
    assert cli_main(["train", "predict"] + args) == 0
    (npz,) = tmp_path.rglob("predictions/*.npz")
    got = np.load(npz)
    seq = store.load_sequence(root / "sequences" / npz.name)
    assert got["positions"].shape == np.asarray(seq["positions"]).shape
    assert got["frames"].tolist() == list(range(len(seq["positions"])))


# ------------------------------------------------------------------ OBJ encodings
def test_obj_with_crlf_bom_and_latin1_reads_like_trimesh(tmp_path):
    body = ("# caf\xe9 cr\xe9\xe9 par l'exportateur\r\nv 0 0 0\r\nv 1 0 0\r\nv 0 1 0\r\n"
            "v 1 1 0\r\nf 1 2 3\r\nf 2 4 3\r\n")
    p = tmp_path / "g.obj"
    p.write_bytes(b"\xef\xbb\xbf" + body.encode("latin-1"))
    g = load_garment(p)
    ref = trimesh.load(str(p), force="mesh", process=False)
    assert np.allclose(g.vertices.numpy(), ref.vertices)
    assert np.array_equal(g.faces.numpy(), ref.faces)


# ------------------------------------------------------------------ CLI
def test_train_with_missing_data_root_is_one_line(tmp_path, capsys):
    missing = tmp_path / "nope"
    rc = cli_main(["train", "fit", "--config", CONFIG, "--data.root", str(missing)])
    err = capsys.readouterr().err.strip().splitlines()
    assert rc == 2 and len(err) == 1
    assert str(missing) in err[0] and "garmentgnn generate" in err[0]


def test_version_flag():
    r = subprocess.run([sys.executable, "-m", "garmentgnn.cli", "--version"],
                       capture_output=True, text=True, env=env(), timeout=120)
    assert r.returncode == 0 and r.stdout.strip() == f"garmentgnn {garmentgnn.__version__}"



# ------------------------------------------------------------------ units, builders, OBJ
@pytest.mark.parametrize("scale, advice", [
    (83.0, "looks like centimetres: scale the vertices by 0.01 (e.g. garment.vertices * 0.01)"),
    (3000.0, "looks like millimetres: scale the vertices by 0.001 (e.g. garment.vertices * "
             "0.001)"),
    (20.0, "looks like inches: scale the vertices by 0.0254"),
    (2.1e6, "the unit cannot be told from the size"),
])
def test_unit_advice_gives_one_factor_that_fits(scale, advice):
    """A 0.3 m patch 24.8 units across was told "centimetres ... by 0.01 (e.g. * 0.001)";
    one 6.3e5 units across "by 0.001", still 630 m.  Oracle: the advised factor brings the
    garment to 0.1-2.5 m."""
    g = patch(size=0.3, at=(0, 0, 0.31))
    big = Garment(g.vertices * scale, g.faces, g.uv)
    with pytest.raises(ValueError) as info:
        simulate(big, None, still(2), material("silk"))
    msg = str(info.value)
    assert advice in msg and msg.count("0.0") <= 2, msg
    if "by " in msg:
        factor = float(msg.split("by ")[1].split()[0])
        assert 0.1 <= 0.3 * scale * factor <= 2.5


def test_make_garment_without_a_body_names_body():
    """Was AttributeError: 'NoneType' object has no attribute 'skeleton'."""
    with pytest.raises(TypeError, match="`body`: expected a Body"):
        make_garment("dress", None)


def test_obj_quads_sharing_an_edge_through_copies_of_vertices_warn(tmp_path, caplog):
    """Two quads meeting along x = 0.1 with that edge's vertices written twice: two
    separate pieces, without a word before; now a warning with the count, and
    repair=True welds them (oracle: one connected piece, 6 vertices)."""
    p = tmp_path / "quads.obj"
    p.write_text("v 0 0 0.3\nv 0.1 0 0.3\nv 0.1 0.1 0.3\nv 0 0.1 0.3\n"
                 "v 0.1 0 0.3\nv 0.2 0 0.3\nv 0.2 0.1 0.3\nv 0.1 0.1 0.3\n"
                 "f 1 2 3 4\nf 5 6 7 8\n")
    with caplog.at_level(logging.WARNING, logger="garmentgnn.garments.io"):
        g = load_garment(p)
    assert len(g.vertices) == 8
    assert "2 vertices lie on another vertex" in caplog.text and "repair=True" in caplog.text
    welded = load_garment(p, repair=True)
    tm = trimesh.Trimesh(welded.vertices.numpy(), welded.faces.numpy(), process=False)
    assert len(welded.vertices) == 6 and len(tm.split(only_watertight=False)) == 1


# ------------------------------------------------------------------ sequence files, manifests
def test_sequence_check_catches_each_reordering(root):  # noqa: F811
    """Oracle: the file as written passes; positions reordered, or rest vertices and
    positions reordered together (faces left), or one vertex short, each do not."""
    rec = next(r for r in read_manifest(root)["items"] if r["status"] == "ok")
    seq = store.load_record_sequence(root, rec)
    assert store.check_sequence(seq, rec["id"]) is None
    perm = np.random.default_rng(1).permutation(seq["garment_vertices"].shape[0])
    moved = dict(seq, positions=seq["positions"][:, perm])
    assert "vertex order of positions" in store.check_sequence(moved)
    both = dict(seq, positions=seq["positions"][:, perm],
                garment_vertices=seq["garment_vertices"][perm])
    assert "vertex order of garment_vertices" in store.check_sequence(both)
    short = dict(seq, positions=seq["positions"][:, :-1])
    assert "positions have shape" in store.check_sequence(short)


def test_obj_writer_refuses_faces_past_the_vertex_list(tmp_path):
    P, F = np.zeros((2, 3, 3)), np.array([[0, 1, 3]])
    with pytest.raises(ValueError, match="`faces`: reference vertices 0..3 but `positions`"):
        write_obj_sequence(tmp_path / "o", P, F)
    assert not (tmp_path / "o").exists()


def test_duplicate_manifest_ids_are_refused_not_trained_on(root, tmp_path):  # noqa: F811
    """The data module trained on every listed copy (195 -> 240 chunks) before."""
    out = tmp_path / "d"
    shutil.copytree(root, out)
    doc = json.loads((out / store.MANIFEST).read_text())
    doc["items"] = doc["items"] + doc["items"][:1]
    (out / store.MANIFEST).write_text(json.dumps(doc))
    with pytest.raises(ValueError, match=rf"1 id\(s\) listed more than once \('"
                                         rf"{doc['items'][0]['id']}' x2\)"):
        SequenceChunks(out, None, chunk=4, history=2, nystrom_dim=NY)


def test_rebuild_manifest_of_a_folder_without_sequences_writes_nothing(tmp_path):
    """`rebuild_manifest` on a folder without `sequences/` wrote an empty manifest.json
    there and returned: an empty dataset, read as one by every later reader."""
    (tmp_path / "notes.txt").write_text("not a dataset")
    with pytest.raises(ValueError, match=r"^`out`: .* holds no dataset \(no sequences/"):
        store.rebuild_manifest(tmp_path)
    with pytest.raises(ValueError, match=r"^`out`: .*: no such folder"):
        store.rebuild_manifest(tmp_path / "nosuch")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["notes.txt"]

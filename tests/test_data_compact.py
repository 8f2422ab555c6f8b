"""The compact dataset copy (``garmentgnn.data.compact``): positions within 0.1 mm, every
other array bit for bit, the same model inputs, the size-limited subset, bad arguments."""
import itertools
import json
import shutil
import zipfile

import numpy as np
import pytest
import torch

from garmentgnn.body import anny_body
from garmentgnn.data import SequenceChunks, generate, preset, store
from garmentgnn.data import compact

from garmentgnn.sim.stand_in import skinned_wobble

TOL = 1e-4


@pytest.fixture(scope="module")
def root(tmp_path_factory):
    """The tiny preset (train and test splits) with the LBS test double."""
    out = tmp_path_factory.mktemp("tiny")
    s = generate(preset("tiny"), out, workers=0, simulate_fn=skinned_wobble, progress=False)
    assert s.done == 8 and s.failed == 0
    return out


@pytest.fixture(scope="module")
def packed(root, tmp_path_factory):
    tmp = tmp_path_factory.mktemp("packed")
    res = compact.pack(root, tmp / "tiny.zip")
    back = compact.unpack(tmp / "tiny.zip", tmp / "back", cache_dir=tmp / "cache")
    return res, back, tmp


def arrays(path):
    with np.load(path, allow_pickle=False) as z:
        return {k: z[k] for k in z.files}


def test_round_trip_keeps_every_array(root, packed):
    res, back, tmp = packed
    src = store.read_manifest(root)
    assert res.left_out == [] and len(res.sequences) == 8
    assert res.splits == {"train": 4, "test": 4}
    worst = 0.0
    for rec in src["items"]:
        a = arrays(store.sequence_path(root, rec))
        b = arrays(tmp / "back" / "sequences" / f"{rec['id']}.npz")
        assert sorted(a) == sorted(b)
        for k in a:
            assert a[k].dtype == b[k].dtype and a[k].shape == b[k].shape, k
            if k == "positions":
                err = float(np.abs(a[k].astype(np.float64) - b[k]).max())
                assert 0 < err <= TOL  # quantised (not a copy), within 0.1 mm
                worst = max(worst, err)
            else:
                assert np.array_equal(a[k], b[k]), k  # meta_json bytes included
    assert res.max_position_error_m == pytest.approx(worst)


def test_unpacked_manifest_records_the_source(root, packed):
    res, back, tmp = packed
    src, new = store.read_manifest(root), store.read_manifest(tmp / "back")
    assert new["compact"]["source_content_sha256"] == src["content_sha256"] \
        == back.source_content_sha256 == res.source_content_sha256
    assert new["content_sha256"] == back.content_sha256 != src["content_sha256"]
    assert new["counts"] == src["counts"]
    assert new["compact"]["max_position_error_m"] <= TOL and new["compact"]["left_out"] == []
    old = {r["id"]: r for r in src["items"]}
    for r in new["items"]:
        assert r["source_sha256"] == old[r["id"]]["sha256"]
        assert r["sha256"] == store.file_sha256(tmp / "back" / r["file"])
        same = {k for k in old[r["id"]] if k not in ("sha256",)}
        assert {k: r[k] for k in same} == {k: old[r["id"]][k] for k in same}
    assert json.loads((tmp / "back" / "spec.json").read_text()) == \
        json.loads((root / "spec.json").read_text())


@pytest.mark.parametrize("split", ["train", "test"])
def test_sequence_chunks_read_both_alike(root, packed, split):
    tmp = packed[2]
    kw = dict(chunk=4, history=2, nystrom_dim=8, num_landmarks=16)
    a, b = SequenceChunks(root, split, **kw), SequenceChunks(tmp / "back", split, **kw)
    assert [r["id"] for r in a.records] == [r["id"] for r in b.records]  # the same order
    assert len(a) == len(b) and a.frame_counts() == b.frame_counts()
    for i in range(len(a)):
        x, y = a[i], b[i]
        assert x.seq_id == y.seq_id and sorted(x.keys()) == sorted(y.keys())
        for k in x.keys():
            if not torch.is_tensor(x[k]):
                continue
            if k == "gt":
                assert (x[k] - y[k]).abs().max() <= TOL
            elif x[k].is_floating_point():
                assert torch.allclose(x[k], y[k], rtol=0, atol=1e-6), k
            else:
                assert torch.equal(x[k], y[k]), k


def test_pack_is_deterministic(root, packed, tmp_path):
    res = compact.pack(root, tmp_path / "again.zip")
    assert (tmp_path / "again.zip").read_bytes() == (packed[2] / "tiny.zip").read_bytes()
    assert res.bytes == (tmp_path / "again.zip").stat().st_size


def test_quantisation_error_and_wrapping():
    g = np.random.default_rng(0)
    p = g.uniform(-1.5, 2.0, (6, 50, 3)).astype(np.float32)
    p[1::2] *= -1  # every frame jumps across the whole range: differences wrap
    delta, off, scale = compact.quantise(p)
    assert delta.dtype == np.uint16
    back = compact.dequantise(delta, off, scale)
    step = (p.reshape(-1, 3).max(0) - p.reshape(-1, 3).min(0)) / 65535
    assert (np.abs(back - p) <= step / 2 + 1e-6).all()
    flat = np.full((3, 4, 3), 0.25, np.float32)  # no range at all
    assert np.array_equal(compact.dequantise(*compact.quantise(flat)), flat)


def test_a_run_across_14_m_packs_about_its_root(root, tmp_path):
    """A body that runs 14 m in 60 frames (a `learn` item): its garment spans 14 m in the
    world but under 2 m about the root, so it packs within 0.1 mm (16 bits over 14 m
    would be off by 0.11 mm, which was refused)."""
    data = tmp_path / "far"
    shutil.copytree(root, data)
    rec = json.loads((data / "manifest.json").read_text())["items"][0]
    path = store.sequence_path(data, rec)
    a = arrays(path)
    T = a["positions"].shape[0]
    shift = np.zeros((T, 3), np.float32)
    shift[:, 1] = -np.linspace(0.0, 14.0, T, dtype=np.float32)
    a["positions"] = a["positions"] + shift[:, None, :]
    a["motion_translation"] = a["motion_translation"] + shift
    meta = json.loads(a.pop("meta_json").tobytes().decode())
    store.write_sequence(path, a, meta)
    store.rebuild_manifest(data)
    delta, off, scale = compact.quantise(a["positions"])  # without the root: over 0.1 mm
    assert np.abs(compact.dequantise(delta, off, scale) - a["positions"]).max() > TOL
    res = compact.pack(data, tmp_path / "far.zip")
    assert res.max_position_error_m <= TOL
    compact.unpack(tmp_path / "far.zip", tmp_path / "back", cache_dir=tmp_path / "c")
    got = arrays(store.sequence_path(tmp_path / "back", rec))
    assert np.abs(got["positions"] - a["positions"]).max() <= TOL
    assert np.array_equal(got["motion_translation"], a["motion_translation"])


def test_a_span_over_the_tolerance_is_refused(root, tmp_path):
    with pytest.raises(ValueError, match="`tolerance`.*off by up to"):
        compact.pack(root, tmp_path / "x.zip", tolerance=1e-7)
    assert not (tmp_path / "x.zip").exists()


def member_costs(path):
    with zipfile.ZipFile(path) as zf:
        return {i.filename: i.compress_size + 76 + 2 * len(i.filename)
                for i in zf.infolist()}


def test_max_bytes_packs_the_most_sequences_that_fit(root, packed, tmp_path):
    full = packed[2] / "tiny.zip"
    costs = member_costs(full)
    seqs = {n.split("/")[1][:-4]: c for n, c in costs.items() if n.startswith("sequences/")}
    split = {r["id"]: r["split"] for r in store.read_manifest(root)["items"]}
    fixed = full.stat().st_size - sum(seqs.values())  # the index of every sequence, bounded
    limit = full.stat().st_size - sum(sorted(seqs.values())[-3:]) + 10
    # oracle: every subset with each split in it that fits beside that index
    best = max(len(s) for n in range(len(seqs) + 1) for s in itertools.combinations(seqs, n)
               if {split[i] for i in s} == {"train", "test"}
               and fixed + sum(seqs[i] for i in s) <= limit)
    res = compact.pack(root, tmp_path / "part.zip", max_bytes=limit)
    assert res.bytes == (tmp_path / "part.zip").stat().st_size <= limit
    assert len(res.sequences) == best < 8
    assert sorted(res.sequences + res.left_out) == sorted(seqs)
    assert set(res.splits) == {"train", "test"}
    again = compact.pack(root, tmp_path / "part2.zip", max_bytes=limit)
    assert again.sequences == res.sequences
    back = compact.unpack(tmp_path / "part.zip", tmp_path / "back", cache_dir=tmp_path / "c")
    man = store.read_manifest(tmp_path / "back")
    assert back.sequences == len(res.sequences) == man["counts"]["ok"]
    assert man["compact"]["left_out"] == res.left_out
    for s in ("train", "test"):
        SequenceChunks(tmp_path / "back", s, chunk=4, history=2, nystrom_dim=8,
                       num_landmarks=16)
    with pytest.raises(ValueError, match="`max_bytes`.*raise max_bytes by"):
        compact.pack(root, tmp_path / "none.zip", max_bytes=fixed + min(seqs.values()))


def test_splits_choose_what_is_packed(root, tmp_path):
    res = compact.pack(root, tmp_path / "t.zip", splits=["test"])
    assert res.splits == {"test": 4}
    compact.unpack(tmp_path / "t.zip", tmp_path / "t", cache_dir=tmp_path / "c")
    with pytest.raises(ValueError, match="no 'train' split"):
        SequenceChunks(tmp_path / "t", "train")


def test_ids_pack_exactly_those_sequences(root, tmp_path):
    """A one-sequence sample: that sequence's arrays come back as a whole-dataset pack
    gives them, and nothing else is in it."""
    man = json.loads((root / "manifest.json").read_text())
    one = sorted(r["id"] for r in man["items"] if r["split"] == "test")[1]
    res = compact.pack(root, tmp_path / "one.zip", ids=[one, one])
    assert res.sequences == [one] and res.splits == {"test": 1} and not res.left_out
    compact.unpack(tmp_path / "one.zip", tmp_path / "one", cache_dir=tmp_path / "c")
    compact.pack(root, tmp_path / "all.zip")
    compact.unpack(tmp_path / "all.zip", tmp_path / "all", cache_dir=tmp_path / "c")
    a, b = SequenceChunks(tmp_path / "one", "test"), SequenceChunks(tmp_path / "all", "test")
    assert [r["id"] for r in a.records] == [one]
    j = [r["id"] for r in b.records].index(one)
    assert torch.equal(a[0].gt, b[j].gt) and torch.equal(a[0].body_pos, b[j].body_pos)
    with pytest.raises(ValueError, match="`ids`: \\['nope'\\] not among"):
        compact.pack(root, tmp_path / "x.zip", ids=["nope"])
    with pytest.raises(ValueError, match="`ids`"):
        compact.pack(root, tmp_path / "x.zip", splits=["train"], ids=[one])
    with pytest.raises(TypeError, match="`ids`: expected a list"):
        compact.pack(root, tmp_path / "x.zip", ids=one)


def test_anny_body_cache_files_travel(root, tmp_path, monkeypatch):
    data = tmp_path / "anny"
    shutil.copytree(root, data)
    man = json.loads((data / "manifest.json").read_text())
    man["items"][0]["body"] = {"model": "anny", "shape": "thin"}
    man["items"][1]["body"] = {"model": "anny", "shape": "fat"}
    (data / "manifest.json").write_text(json.dumps(man))
    monkeypatch.setenv("GARMENTGNN_CACHE_DIR", str(tmp_path / "cache"))
    for shape, payload in (("thin", b"thin body"), ("regular", b"regular body")):
        p = anny_body.body_cache_path(shape)
        p.parent.mkdir(parents=True, exist_ok=True)
        p.write_bytes(payload)
    res = compact.pack(data, tmp_path / "a.zip")
    assert res.bodies == sorted(f"bodies/anny/{anny_body.body_cache_path(s).name}"
                                for s in ("thin", "regular"))
    assert res.missing_bodies == [f"bodies/anny/{anny_body.body_cache_path('fat').name}"]
    back = compact.unpack(tmp_path / "a.zip", tmp_path / "u", cache_dir=tmp_path / "other")
    assert len(back.bodies) == 2
    for shape, payload in (("thin", b"thin body"), ("regular", b"regular body")):
        name = anny_body.body_cache_path(shape).name
        assert (tmp_path / "other" / "anny" / name).read_bytes() == payload
    # a cache file already there is kept, a missing one written
    (tmp_path / "other" / "anny" / name).write_bytes(b"kept")
    thin = tmp_path / "other" / "anny" / anny_body.body_cache_path("thin").name
    thin.unlink()
    again = compact.unpack(tmp_path / "a.zip", tmp_path / "u2", cache_dir=tmp_path / "other")
    assert again.bodies == [str(thin)] and thin.read_bytes() == b"thin body"
    assert (tmp_path / "other" / "anny" / name).read_bytes() == b"kept"


@pytest.mark.parametrize("kw, err, match", [
    ({"splits": "train"}, TypeError, "`splits`: expected a list"),
    ({"splits": ["train", "nope"]}, ValueError, "`splits`: .* no ok sequences in \\['nope'\\]"),
    ({"splits": []}, ValueError, "`splits`"),
    ({"max_bytes": 1.5e6}, TypeError, "`max_bytes`: expected an int"),
    ({"max_bytes": True}, TypeError, "`max_bytes`"),
    ({"max_bytes": 0}, ValueError, "`max_bytes`: expected a positive"),
    ({"max_bytes": 100}, ValueError, "`max_bytes`: the smallest"),
    ({"tolerance": -1.0}, ValueError, "`tolerance`"),
    ({"tolerance": "0.1"}, TypeError, "`tolerance`"),
])
def test_bad_pack_arguments(root, tmp_path, kw, err, match):
    with pytest.raises(err, match=match):
        compact.pack(root, tmp_path / "x.zip", **kw)
    assert not (tmp_path / "x.zip").exists()


def test_bad_paths(root, packed, tmp_path):
    with pytest.raises(ValueError, match="`out_file`: .* is a folder"):
        compact.pack(root, tmp_path)
    with pytest.raises(FileNotFoundError, match="make the dataset"):
        compact.pack(tmp_path / "missing", tmp_path / "x.zip")
    with pytest.raises(ValueError, match="`root`: .* not an empty folder"):
        compact.unpack(packed[2] / "tiny.zip", root)
    with pytest.raises(FileNotFoundError, match="`file`: .* does not exist"):
        compact.unpack(tmp_path / "nope.zip", tmp_path / "u")
    (tmp_path / "bad.zip").write_bytes(b"not a zip")
    with pytest.raises(ValueError, match="`file`: .* is not a packed dataset"):
        compact.unpack(tmp_path / "bad.zip", tmp_path / "u")
    with zipfile.ZipFile(tmp_path / "other.zip", "w") as zf:
        zf.writestr("compact.json", json.dumps({"format": "something else"}))
    with pytest.raises(ValueError, match="not a garmentgnn-compact file"):
        compact.unpack(tmp_path / "other.zip", tmp_path / "u")
    assert not (tmp_path / "u").exists()


def test_command_line(root, tmp_path, capsys):
    assert compact.main(["pack", str(root), str(tmp_path / "c.zip"), "--splits", "test"]) == 0
    assert json.loads(capsys.readouterr().out)["splits"] == {"test": 4}
    assert compact.main(["unpack", str(tmp_path / "c.zip"), str(tmp_path / "u"),
                         "--cache-dir", str(tmp_path / "cache")]) == 0
    assert json.loads(capsys.readouterr().out)["sequences"] == 4
    assert compact.main(["unpack", str(tmp_path / "c.zip"), str(tmp_path / "u")]) == 2
    assert "not an empty folder" in capsys.readouterr().err

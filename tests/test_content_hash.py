"""The dataset content hash: over the sequence files' bytes, in the manifest, printed by
``garmentgnn generate`` and ``garmentgnn manifest``."""
import hashlib
import shutil
from pathlib import Path

import numpy as np
import pytest

from garmentgnn.bench.learned import prepare_dataset
from garmentgnn.cli import main as cli_main
from garmentgnn.data import generate, preset, read_manifest
from garmentgnn.data import store

from test_data import fake_simulate


def recompute(root):
    """An independent content hash: each ``sequences/<id>.npz``'s bytes hashed here, the
    lines ``"<id> <hex>\\n"`` sorted by id."""
    lines = sorted(f"{p.stem} {hashlib.sha256(p.read_bytes()).hexdigest()}\n"
                   for p in (Path(root) / "sequences").glob("*.npz"))
    return hashlib.sha256("".join(lines).encode()).hexdigest()


@pytest.fixture(scope="module")
def made(tmp_path_factory):
    out = tmp_path_factory.mktemp("hash")
    summary = generate(preset("tiny"), out, workers=0, simulate_fn=fake_simulate,
                       progress=False)
    assert summary.done == 8
    return out, summary


def test_manifest_and_summary_carry_the_recomputed_hash(made):
    out, summary = made
    man = read_manifest(out)
    want = recompute(out)
    assert man["content_sha256"] == want == summary.content_sha256
    assert f"dataset content SHA-256: {want}" in str(summary)
    # a second run over the finished folder skips every item and reports the same hash
    again = generate(preset("tiny"), out, workers=0, simulate_fn=fake_simulate,
                     progress=False)
    assert again.skipped == 8 and again.content_sha256 == want


def test_independent_of_item_order(made):
    items = read_manifest(made[0])["items"]
    h = store.content_sha256(items)
    assert store.content_sha256(items[::-1]) == h
    assert store.content_sha256(items[3:] + items[:3]) == h
    # pending / failed items do not count; an ok item without a file hash gives None
    assert store.content_sha256(items + [dict(items[0], id="x", status="pending",
                                              sha256=None)]) == h
    assert store.content_sha256(items[1:]) != h
    assert store.content_sha256([dict(items[0], sha256=None)] + items[1:]) is None


def test_one_changed_file_changes_it_and_manifest_prints_it(made, tmp_path, capsys):
    out = tmp_path / "copy"
    shutil.copytree(made[0], out)
    before = read_manifest(out)["content_sha256"]
    rec = read_manifest(out)["items"][5]
    path = out / rec["file"]
    seq = store.load_sequence(path)
    meta = seq.pop("meta")
    seq["positions"] = seq["positions"] + np.float32(1e-7)  # 0.1 um: another CPU's rounding
    store.write_sequence(path, seq, meta)
    assert cli_main(["manifest", "--out", str(out)]) == 0
    printed = capsys.readouterr().out
    after = read_manifest(out)["content_sha256"]
    assert after != before and after == recompute(out)
    assert f"dataset content SHA-256: {after}" in printed
    # the untouched copy's manifest, rebuilt from its files, keeps the generated hash
    assert store.rebuild_manifest(made[0], write=False)["items"] and \
        store.content_sha256(store.rebuild_manifest(made[0], write=False)["items"]) == before


def test_bench_dataset_info_quotes_it(made):
    info = prepare_dataset(made[0])
    assert info.content_sha256 == recompute(made[0])
    assert info.to_json()["content_sha256"] == info.content_sha256
    assert info.to_json()["root"] == str(made[0])

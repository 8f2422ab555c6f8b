"""The Nyström features kept beside a dataset (``ROOT/processed``): the same features as
computed from the sequence file's mesh, read back by a later run, recomputed where the
file is cut off, and not needed where the dataset cannot be written."""
import numpy as np
import pytest
import torch

from garmentgnn.data import SequenceChunks, store
from garmentgnn.geometry import geodesic_nystrom_features
from garmentgnn.models.inputs import build_static

from conftest import skirt_dataset


@pytest.fixture(scope="module")
def root(tmp_path_factory):
    return skirt_dataset(tmp_path_factory.mktemp("data"), ["walk", "run"], 8, name="proc")


def _reference(chunks: SequenceChunks, i: int, k: int = 16) -> torch.Tensor:
    """The oracle: the features of the sequence file's mesh, computed here."""
    seq = chunks.sequence(i)
    pos = torch.from_numpy(np.asarray(seq["garment_vertices"], np.float32))  # as stored
    faces = torch.from_numpy(np.asarray(seq["garment_faces"])).long()
    return geodesic_nystrom_features(pos.double(), faces, k=k, num_landmarks=64).float()


def test_nystrom_features_are_kept_and_read_back(root, monkeypatch):
    first = SequenceChunks(root, "train", chunk=4)
    ref = _reference(first, 0)
    path = first.nystrom_path(0)
    assert not path.exists()
    assert torch.equal(first.static(0).nystrom, ref)
    assert path.is_file() and first.num_nystrom_builds == 1
    assert path.parent.parent == root / "processed"

    later = SequenceChunks(root, "train", chunk=4)  # another run: read, not computed

    def fail(*a, **kw):
        raise AssertionError("computed again")

    monkeypatch.setattr("garmentgnn.data.chunks.nystrom_features", fail)
    assert torch.equal(later.static(0).nystrom, ref)
    assert later.num_nystrom_builds == 0 and later.num_static_builds == 1
    monkeypatch.undo()

    other = SequenceChunks(root, "train", chunk=4, nystrom_dim=8)  # other settings: own file
    assert other.nystrom_path(0) != path
    assert torch.equal(other.static(0).nystrom, _reference(other, 0, k=8))
    assert other.num_nystrom_builds == 1


def test_a_cut_off_or_unwritable_file_is_computed_again(root, monkeypatch):
    chunks = SequenceChunks(root, "train", chunk=4)
    ref = _reference(chunks, 1)
    chunks.static(1)
    path = chunks.nystrom_path(1)
    path.write_bytes(path.read_bytes()[:60])  # a write cut off by a kill
    again = SequenceChunks(root, "train", chunk=4)
    assert torch.equal(again.static(1).nystrom, ref) and again.num_nystrom_builds == 1
    assert np.array_equal(np.load(path), ref.numpy())  # written whole again
    np.save(path, ref.numpy()[:, :3])  # features of other settings under this name
    assert torch.equal(SequenceChunks(root, "train", chunk=4).static(1).nystrom, ref)

    path.unlink()

    def read_only(*a, **kw):
        raise PermissionError("read-only file system")

    monkeypatch.setattr(store, "atomic_write_bytes", read_only)
    ro = SequenceChunks(root, "train", chunk=4)
    assert torch.equal(ro.static(1).nystrom, ref) and not path.exists()


def test_build_static_checks_given_features(root):
    chunks = SequenceChunks(root, "train", chunk=4)
    st, body = chunks._static_and_body(0)
    with pytest.raises(ValueError, match="`nystrom`"):
        build_static(st.rest_pos, st.faces, body, st.skin_weights, nystrom=st.nystrom[:, :4])

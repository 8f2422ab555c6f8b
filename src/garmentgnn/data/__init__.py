"""Dataset specs and presets (garments x bodies x motions x materials), their generation
through the simulator, the on-disk store (sequence files, manifest), export (PC2, OBJ,
glTF) and a lazy PyG dataset.

The PyG dataset classes are imported on first use so that the CLI and the generator
do not pay for importing torch_geometric."""
from garmentgnn.data.export import export_sequence, write_obj_sequence, write_pc2
from garmentgnn.data.generate import SpecMismatch, Summary, generate
from garmentgnn.data.keys import body_key, garment_key, motion_key
from garmentgnn.data.presets import PRESETS, Spec, preset
from garmentgnn.data.worker import run_item
from garmentgnn.data.store import (
    IntegrityError,
    file_sha256,
    load_record_sequence,
    load_sequence,
    read_manifest,
    rebuild_manifest,
    validate_sequence,
)

__all__ = ["GarmentFrame", "GarmentSequenceDataset", "IntegrityError", "PRESETS", "Spec",
           "SpecMismatch", "Summary", "body_key", "export_sequence", "file_sha256",
           "garment_key", "generate", "load_record_sequence", "load_sequence", "motion_key",
           "preset", "read_manifest", "rebuild_manifest", "run_item", "validate_sequence",
           "write_obj_sequence", "write_pc2"]


def __getattr__(name):
    if name in ("GarmentFrame", "GarmentSequenceDataset"):
        from garmentgnn.data import dataset
        return getattr(dataset, name)
    raise AttributeError(f"module 'garmentgnn.data' has no attribute {name!r}")

"""Dataset specs and presets (garments x bodies x motions x materials), their generation
through an engine, the on-disk store (sequence files, manifest) and export (PC2, OBJ,
glTF, Alembic, .blend), and the reader that makes model inputs of it,
:class:`SequenceChunks`."""
from garmentgnn.data.chunks import DEFAULT_DENSITY, SequenceChunks
from garmentgnn.data.export import export_sequence, write_obj_sequence, write_pc2
from garmentgnn.data.generate import SpecMismatch, Summary, generate
from garmentgnn.data.keys import body_key, garment_key, motion_key
from garmentgnn.data.presets import PRESETS, Spec, preset
from garmentgnn.data.validity import VALID_PENETRATION, sequence_valid, valid_frames
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

__all__ = ["DEFAULT_DENSITY", "IntegrityError", "PRESETS", "SequenceChunks", "Spec", "SpecMismatch",
           "Summary", "VALID_PENETRATION", "body_key", "export_sequence", "file_sha256",
           "garment_key", "generate", "load_record_sequence", "load_sequence", "motion_key",
           "preset", "read_manifest", "rebuild_manifest", "run_item", "sequence_valid",
           "valid_frames", "validate_sequence", "write_obj_sequence", "write_pc2"]


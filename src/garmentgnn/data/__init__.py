"""Dataset generation (garments x bodies x motions x materials through an engine) and
the on-disk store (sequence files, manifest, PC2/OBJ/glTF export).  The model inputs
read from it are :class:`garmentgnn.training.SequenceChunks`'s."""
from garmentgnn.data.generate import (
    PRESETS,
    Spec,
    SpecMismatch,
    Summary,
    body_key,
    garment_key,
    generate,
    motion_key,
    preset,
    run_item,
)
from garmentgnn.data.store import (
    IntegrityError,
    export_sequence,
    file_sha256,
    load_record_sequence,
    load_sequence,
    read_manifest,
    rebuild_manifest,
    validate_sequence,
    write_obj_sequence,
    write_pc2,
)

__all__ = ["IntegrityError", "PRESETS", "Spec",
           "SpecMismatch", "Summary", "body_key", "export_sequence", "file_sha256",
           "garment_key", "generate", "load_record_sequence", "load_sequence", "motion_key",
           "preset", "read_manifest", "rebuild_manifest", "run_item", "validate_sequence",
           "write_obj_sequence", "write_pc2"]


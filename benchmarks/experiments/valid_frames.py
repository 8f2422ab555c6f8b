"""Which share of each dataset's frames is valid ground truth: per generated dataset and
split, the frames the engine did not converge on, the frames with the garment deeper than
:data:`~garmentgnn.data.validity.VALID_PENETRATION` inside the body, the share left out of
training targets and scores, and what the generator's re-simulation did.

The mask is the one every loader reads (:func:`garmentgnn.data.validity.sequence_valid`
of each sequence file), so the table follows today's line, not the manifest's counts of
the day each file was written.  Writes JSON and markdown into a cache folder, ``--commit``
the committed ``docs/results/benchmarks/valid_frames.{json,md}``::

    python benchmarks/experiments/valid_frames.py \\
        --data ~/.cache/garmentgnn/datasets/learn-blender \\
        ~/.cache/garmentgnn/datasets/small-blender --commit
"""
from __future__ import annotations

from pathlib import Path
from typing import Any, Dict, List

import numpy as np

from garmentgnn._argparse import (Accumulate, ArgumentParser, HelpFormatter, add_output_args,
                                  check_unique, command_line, existing_dir, output_path)
from garmentgnn._files import atomic_write_bytes, atomic_write_json
from garmentgnn.data.store import load_record_sequence, read_manifest
from garmentgnn.data.validity import VALID_PENETRATION, sequence_valid
from garmentgnn.bench.tables import table

COMMITTED = Path(__file__).resolve().parents[2] / "docs" / "results" / "benchmarks" / "valid_frames"
SPLITS = ("train", "val", "test")


def dataset_rows(root: Path) -> List[Dict[str, Any]]:
    """One row per split of the dataset at ``root`` (and ``all``), counted from its files."""
    man = read_manifest(root)
    counts: Dict[str, Dict[str, Any]] = {}
    for rec in man["items"]:
        if rec.get("status") != "ok":
            continue
        seq = load_record_sequence(root, rec, keys=("positions",),
                                   optional=("converged", "penetration"))
        valid = sequence_valid(seq)
        conv = np.ones(valid.shape, bool) if seq.get("converged") is None else \
            np.asarray(seq["converged"], bool)
        pen = seq.get("penetration")
        deep = np.zeros(valid.shape, bool) if pen is None else \
            ~(np.asarray(pen, np.float64) <= VALID_PENETRATION)
        res = rec.get("resimulated") or {}
        for split in (rec["split"], "all"):
            c = counts.setdefault(split, dict(sequences=0, frames=0, not_converged=0, deep=0,
                                              left_out=0, with_invalid=0, resimulated=0,
                                              kept_resimulation=0, deepest_m=0.0))
            c["sequences"] += 1
            c["frames"] += int(valid.size)
            c["not_converged"] += int((~conv).sum())
            c["deep"] += int(deep.sum())
            c["left_out"] += int((~valid).sum())
            c["with_invalid"] += int((~valid).any())
            c["resimulated"] += int(bool(res))
            c["kept_resimulation"] += int(res.get("kept") == "resimulated")
            if pen is not None and len(pen):
                c["deepest_m"] = max(c["deepest_m"], float(np.nanmax(pen)))
    engine = man.get("engine")
    return [dict(dataset=man.get("name"), content_sha256=man.get("content_sha256"),
                 engine=engine.get("name") if isinstance(engine, dict) else engine,
                 split=s, **counts[s])
            for s in (*SPLITS, "all") if s in counts]


def markdown(rows: List[Dict[str, Any]], command: str) -> str:
    body = [[f"{r['dataset']} ({r['engine']})", r["split"], str(r["sequences"]), str(r["frames"]),
             str(r["not_converged"]), str(r["deep"]),
             f"{r['left_out']} ({r['left_out'] / max(r['frames'], 1):.1%})",
             str(r["with_invalid"]), f"{r['resimulated']} ({r['kept_resimulation']} kept)",
             f"{100 * r['deepest_m']:.1f}"] for r in rows]
    hashes = sorted({f"{r['dataset']}: `{(r['content_sha256'] or 'none')[:16]}…`" for r in rows})
    return "\n".join([
        "# Valid ground truth per dataset", "", f"`{command}`", "",
        f"A frame is valid when the engine converged on it and the garment is at most "
        f"{100 * VALID_PENETRATION:g} cm inside the body (`garmentgnn.data.validity`); the "
        "others are left out of the supervised loss and of every score. Re-simulated: the "
        "items the generator simulated again at higher quality (the kept run in brackets).",
        "", *table(["dataset", "split", "sequences", "frames", "not converged",
                    f"deeper than {100 * VALID_PENETRATION:g} cm", "left out",
                    "sequences with a left-out frame", "re-simulated", "deepest (cm)"], body),
        "", "Datasets (content SHA-256): " + ", ".join(hashes), ""])


def main(argv=None) -> None:
    ap = ArgumentParser(description=__doc__.splitlines()[0],
                        formatter_class=HelpFormatter)
    ap.add_argument("--data", nargs="+", required=True, type=existing_dir, action=Accumulate,
                    help="generated dataset folders")
    add_output_args(ap, COMMITTED, "writes OUT.json and OUT.md")
    a = ap.parse_args(argv)
    check_unique(ap, [str(d) for d in a.data], "--data")
    out = output_path(a, COMMITTED)
    rows = [r for d in a.data for r in dataset_rows(Path(d))]
    command = command_line("benchmarks/experiments/valid_frames.py", argv)
    out.parent.mkdir(parents=True, exist_ok=True)
    atomic_write_json(out.with_suffix(".json"), {"command": command, "rows": rows})
    text = markdown(rows, command)
    atomic_write_bytes(out.with_suffix(".md"), text.encode())
    print(text)


if __name__ == "__main__":
    main()

"""Render procedural garments on thin / regular / fat bodies in three poses (PNG).

Each garment is built on each body's rest shape (sized from that body), given
skinning weights transferred from the body, and posed with the body by linear
blend skinning (the paper's Eq. 1: the "LBS only" coarse garment, before any
learned deformation).  One PNG per garment: rows are body shapes, columns poses.

    python examples/render_garments.py                    # anny bodies, all garments
    python examples/render_garments.py --garments dress --out /tmp/renders
    python examples/render_garments.py --body capsule     # no anny needed
"""
from __future__ import annotations

import argparse
import time
from pathlib import Path

import torch

from garmentgnn.body import AnnyBodyModel, CapsuleBodyModel
from garmentgnn.body.lbs import forward_kinematics, linear_blend_skinning
from garmentgnn.garments import make_garment
from garmentgnn.garments.skinning import transfer_skinning_weights
from garmentgnn.motion import make_motion
from garmentgnn.viz import render_grid

SHAPES = ["thin", "regular", "fat"]
POSES = [("rest", None, 0), ("walk", "walk", 8), ("sit", "sit_stand", 45)]
BODY_RGB, GARMENT_RGB = (0.82, 0.70, 0.60), {"dress": (0.25, 0.45, 0.80),
                                              "tshirt": (0.85, 0.35, 0.30),
                                              "trousers": (0.30, 0.55, 0.35),
                                              "skirt": (0.60, 0.35, 0.70),
                                              "jumpsuit": (0.80, 0.60, 0.20)}


def render_garment(kind: str, model, out: Path, resolution: str) -> Path:
    cells, titles = [], []
    for shape in SHAPES:
        body = model(shape)
        garment = make_garment(kind, body, resolution=resolution)
        weights = transfer_skinning_weights(garment.vertices, garment.faces, body.vertices,
                                            body.weights)
        row, row_titles = [], []
        for label, motion_name, frame in POSES:
            if motion_name is None:
                bv, gv = body.vertices, garment.vertices
            else:
                motion = make_motion(motion_name, body.skeleton, num_frames=60,
                                     rest_joints=body.joints)
                rot = motion.rotations[frame:frame + 1].to(body.vertices.dtype)
                tr = motion.translation[frame:frame + 1].to(body.vertices.dtype)
                A, _ = forward_kinematics(rot, body.joints, body.skeleton.parents, tr)
                bv = linear_blend_skinning(body.vertices, body.weights, A)[0]
                gv = linear_blend_skinning(garment.vertices, weights, A)[0]
            row.append([(bv, body.faces, BODY_RGB), (gv, garment.faces, GARMENT_RGB[kind])])
            row_titles.append(f"{kind} / {shape} / {label} ({garment.vertices.shape[0]} v)")
        cells.append(row)
        titles.append(row_titles)
    return render_grid(cells, out / f"{kind}.png", titles=titles, elev=12, azim=-70)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--body", choices=["anny", "capsule"], default="anny")
    ap.add_argument("--garments", nargs="+", default=["dress", "tshirt", "trousers"])
    ap.add_argument("--resolution", default="low")
    ap.add_argument("--out", type=Path, default=Path("docs/renders"))
    args = ap.parse_args()
    torch.manual_seed(0)
    t0 = time.perf_counter()
    model = AnnyBodyModel() if args.body == "anny" else CapsuleBodyModel()
    print(f"body model ({args.body}) ready in {time.perf_counter() - t0:.1f} s")
    for kind in args.garments:
        t0 = time.perf_counter()
        path = render_garment(kind, model, args.out, args.resolution)
        print(f"wrote {path} in {time.perf_counter() - t0:.1f} s")


if __name__ == "__main__":
    main()

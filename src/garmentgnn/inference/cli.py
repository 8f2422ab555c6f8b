"""``garmentgnn predict``: a trained method on your garment, body and motion, written as
glTF (with the body), PC2 and an OBJ sequence (docs/own_garment.md)."""
from __future__ import annotations

import argparse
import json
import sys
import warnings

from garmentgnn._argparse import HelpFormatter, finite_float, int_at_least, nonempty_path


def _mapping(text: str):
    """``--mapping`` as a JSON object or ``FILE_JOINT=BODY_JOINT,...``."""
    text = text.strip()
    if text.startswith("{"):
        try:
            value = json.loads(text)
        except json.JSONDecodeError as exc:
            raise argparse.ArgumentTypeError(f"not a JSON object ({exc})") from None
        if not isinstance(value, dict):
            raise argparse.ArgumentTypeError("expected a JSON object {file joint: body joint}")
        return {str(k): str(v) for k, v in value.items()}
    pairs = [p for p in text.split(",") if p.strip()]
    if not pairs or not all("=" in p for p in pairs):
        raise argparse.ArgumentTypeError("expected FILE_JOINT=BODY_JOINT[,...] or a JSON "
                                         "object")
    return dict((a.strip(), b.strip()) for a, b in (p.split("=", 1) for p in pairs))


def add_parser(sub) -> argparse.ArgumentParser:
    p = sub.add_parser("predict", help="a trained method on your garment (mesh or template), "
                       "body and motion (BVH or generator): glTF, PC2, OBJs",
                       description=__doc__, formatter_class=HelpFormatter)
    which = p.add_mutually_exclusive_group(required=True)
    which.add_argument("--ckpt", type=nonempty_path, default=None,
                       help="a checkpoint of any learned method (GarTrans, DA/HOOD/NCS-style, "
                            "MGN-style)")
    which.add_argument("--method", choices=("lbs",), default=None,
                       help="lbs: the rest garment skinned to the body, no checkpoint")
    p.add_argument("--start-from", type=nonempty_path, default=None, metavar="CKPT",
                   help="MGN-style --ckpt: roll out from the first two frames this "
                        "frame-parallel checkpoint (DA-style, GarTrans, ...) predicts instead "
                        "of the skinned garment (default: the skinned garment)")
    p.add_argument("--garment", required=True,
                   help="a mesh file (OBJ, PLY, glTF) or a template name (skirt, dress, ...)")
    p.add_argument("--body", default="regular",
                   help="anny's named shape (thin, regular, fat, ...), MODEL:SHAPE "
                        "(capsule:regular) or anny's 6 comma-separated shape parameters")
    p.add_argument("--motion", required=True,
                   help="a BVH file or a generator name (walk, run, twirl, ...)")
    p.add_argument("--out", required=True, type=nonempty_path,
                   help="a folder (prediction.glb/.pc2/_obj/ in it) or a file stem")
    p.add_argument("--frames", type=int_at_least(1), default=None,
                   help="frames to predict (default: a BVH's every frame; 60 for a generator)")
    p.add_argument("--fps", type=finite_float, default=30.0,
                   help="frame rate of the prediction (a BVH is resampled to it)")
    p.add_argument("--scale", type=finite_float, default=0.01,
                   help="BVH: metres per file unit (CMU and Mixamo files: 0.01, centimetres)")
    p.add_argument("--up", choices=("Y", "Z"), default="Y", help="BVH: the file's up axis")
    p.add_argument("--mapping", type=_mapping, default=None,
                   help="BVH: file joint -> body joint or role where names differ, "
                        "e.g. pelvis_j=pelvis,thigh_l=l_hip")
    p.add_argument("--start", type=int_at_least(0), default=0,
                   help="BVH: first frame (at --fps)")
    p.add_argument("--material", default="silk", help="fabric of the garment")
    p.add_argument("--resolution", type=int_at_least(200), default=300,
                   help="template: target vertex count")
    p.add_argument("--device", default="cpu", help="cpu or cuda")
    p.add_argument("--compile", choices=("auto", "on", "off"), default="auto",
                   help="GarTrans: compile the collision projection's nearest-face search "
                        "(auto: where the take is long enough to pay the compilation back, "
                        "frames x vertices >= 350,000 on the CPU; always on a GPU)")
    p.add_argument("--no-body", action="store_true", help="glTF: the garment only")
    p.add_argument("--show", action="store_true",
                   help="also render <out>.mp4/.gif/.png of the garment on the body")
    return p


def main(args: argparse.Namespace) -> int:
    from garmentgnn.inference.output import output_paths, write_prediction  # noqa: PLC0415
    from garmentgnn.inference.predict import (ResolutionWarning,  # noqa: PLC0415
                                              predict_garment_motion)
    if args.device.startswith("cuda"):
        import torch  # noqa: PLC0415
        if not torch.cuda.is_available():
            print("error: --device cuda: no CUDA device here; use --device cpu",
                  file=sys.stderr)
            return 2
    paths = output_paths(args.out)  # refused before any work
    body = args.body
    if "," in body:
        try:
            body = [float(x) for x in body.split(",")]
        except ValueError:
            print(f"error: --body {args.body}: expected a shape name or numbers",
                  file=sys.stderr)
            return 2

    def on_frames(t0: int, n: int, seconds: float) -> None:
        if t0 == 0:  # the first call also sets up (and compiles): not a frame's cost
            print(f"frames 0-{n - 1}: {seconds:.3f} s, set-up and any compilation included",
                  flush=True)
            return
        for t in range(t0, t0 + n):
            print(f"frame {t}: {1e3 * seconds / n:.2f} ms", flush=True)

    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always", ResolutionWarning)
        pred = predict_garment_motion(
            args.garment, body, args.motion, ckpt=args.ckpt, method=args.method,
            frames=args.frames, fps=args.fps, material=args.material, device=args.device,
            scale=args.scale, up=args.up, mapping=args.mapping, start=args.start,
            resolution=args.resolution, on_frames=on_frames,
            compile={"auto": None, "on": True, "off": False}[args.compile],
            start_from=args.start_from)
    for w in caught:
        if issubclass(w.category, ResolutionWarning):
            print(f"warning: --garment {args.garment}: {w.message}", file=sys.stderr)
        else:
            warnings.warn_explicit(w.message, w.category, w.filename, w.lineno)
    write_prediction(pred, args.out, body=not args.no_body)
    mode = "autoregressive" if pred.autoregressive else "frame-parallel"
    steady, setup = pred.steady_frame_seconds, pred.setup_seconds
    split = (f": set-up and compilation {setup:.3f} s, then {1e3 * steady:.2f} ms/frame "
             f"(steady state)" if steady is not None else " (one call: set-up included)")
    print(f"{pred.method}, {mode}: {len(pred.positions)} frames of "
          f"{pred.positions.shape[1]} vertices in {pred.total_seconds:.3f} s{split} on "
          f"{args.device}; nearest-face search {'compiled' if pred.compiled else 'eager'}")
    for k in ("glb", "pc2", "obj"):
        print(f"wrote {paths[k]}")
    if args.show:
        from garmentgnn.viz.animate import Panel, render_animation  # noqa: PLC0415
        meshes, fps = _meshes(pred)
        anim = render_animation([Panel(pred.method, pred.positions)], pred.faces,
                                paths["glb"].with_suffix(""), meshes[-1].positions,
                                meshes[-1].faces, fps=fps, caption=pred.method)
        for path in (anim.mp4, anim.gif, anim.still):
            if path is not None:
                print(f"wrote {path}")
    return 0


def _meshes(pred):
    from garmentgnn.data.gltf import sequence_meshes  # noqa: PLC0415
    return sequence_meshes(pred.seq, body=True)

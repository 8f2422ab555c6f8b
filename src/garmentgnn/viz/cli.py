"""``garmentgnn show``: an MP4/GIF (+ PNG still, + glTF, + with ``--html`` a viewer page)
of ground truth | checkpoints | LBS only on one held-out sequence, coloured by per-vertex
error."""
from __future__ import annotations

import argparse
import time

from garmentgnn._argparse import HelpFormatter, int_at_least, nonempty_path


def add_parser(sub) -> argparse.ArgumentParser:
    s = sub.add_parser("show", help="animate ground truth | checkpoints | LBS on a held-out "
                       "sequence (MP4, GIF, PNG, glTF, HTML viewer)", description=__doc__,
                       formatter_class=HelpFormatter)
    s.add_argument("--data", required=True, type=nonempty_path,
                   help="generated dataset folder (manifest.json)")
    s.add_argument("--ckpt", action="append", default=[], metavar="[NAME=]PATH",
                   help="a GarTrans checkpoint to show (repeat for baselines / ablations); "
                   "NAME is the panel title (default: the file name)")
    s.add_argument("--pred", action="append", default=[], metavar="NAME=FILE.npy",
                   help="any other method's garment on this sequence, [T, V, 3] in our vertex "
                   "order (e.g. a bench baseline), shown after the checkpoints")
    s.add_argument("--out", required=True, type=nonempty_path,
                   help="output path without suffix (.mp4/.gif/.png/.glb)")
    s.add_argument("--split", default="test", help="the dataset split of the sequence")
    s.add_argument("--index", type=int, default=0, help="which sequence of the split")
    s.add_argument("--mode", choices=("gartrans", "gartrans_ar"), default="gartrans",
                   help="frame-parallel or autoregressive prediction")
    s.add_argument("--no-lbs", action="store_true", help="leave out the LBS-only panel")
    s.add_argument("--history", type=int_at_least(1), default=None,
                   help="past frames each prediction sees (default: as the checkpoints were "
                        "trained; the data module's default without one)")
    s.add_argument("--num-landmarks", type=int_at_least(1), default=None,
                   help="Nystrom landmarks of the garment's geodesic features (default: as "
                        "the checkpoints were trained; the data module's default without one)")
    s.add_argument("--max-frames", type=int_at_least(1), default=None,
                   help="show at most this many frames (default: the whole sequence)")
    s.add_argument("--height", type=int, default=896, help="frame height in px (>= 720)")
    s.add_argument("--clim", type=float, default=None,
                   help="top of the error scale in cm (default: from the panels that did not "
                        "diverge)")
    s.add_argument("--no-gif", action="store_true", help="write no GIF beside the MP4")
    s.add_argument("--no-gltf", action="store_true", help="write no glTF (.glb) file")
    s.add_argument("--html", action="store_true",
                   help="also write OUT.html, a single-file 3D viewer of the glTF (three.js; "
                        "error colours, labels and colour bar as in the MP4)")
    return s


def main(args: argparse.Namespace) -> int:
    # start-up: the `show` parser is built without loading the training package (lightning)
    from garmentgnn.viz.compare import parse_named, show, unique_names  # noqa: PLC0415
    t0 = time.perf_counter()
    ckpts, preds = parse_named(args.ckpt), parse_named(args.pred, "--pred")
    unique_names(ckpts + preds)
    res = show(args.data, dict(ckpts), args.out, split=args.split,
               index=args.index, mode=args.mode, lbs=not args.no_lbs, history=args.history,
               num_landmarks=args.num_landmarks, max_frames=args.max_frames,
               predictions=dict(preds), gltf=not args.no_gltf,
               height=args.height, gif=not args.no_gif, html=args.html,
               clim=None if args.clim is None else (0.0, args.clim))
    a = res["animation"]
    for p in a.mean_error:
        print(f"{p}: mean E_dist {a.mean_error[p]:.3f} cm")
    for path in (a.mp4, a.gif, a.still, res["gltf"], res["html"]):
        if path is not None:
            print(f"wrote {path}")
    if a.still_error:
        print(f"{a.still.name}: frame {a.still_frame + 1} of {a.frames}, the frame closest to "
              f"the first prediction's median per-frame error; on it: "
              + ", ".join(f"{k} {v:.3f} cm" for k, v in a.still_error.items()))
    if a.diverged:
        print(f"diverged (clipped, left out of the colour scale): {', '.join(a.diverged)}")
    print(f"{a.frames} frames at {a.size[0]}x{a.size[1]} in {time.perf_counter() - t0:.1f} s")
    return 0

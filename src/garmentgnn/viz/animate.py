"""Side-by-side animations of garments on a body (MP4 + GIF + a PNG still).

Each panel is one garment sequence on the same posed body, seen from the same
camera: typically ground truth | GarTrans | baselines | LBS only.  Predicted panels
are coloured by their per-vertex distance to the ground truth (``E_dist`` in cm), all
with one colour scale, shown once as a colour bar under the panels.

Framing (:func:`frame_view`): the camera is fitted to the whole posed body and the
ground truth over every frame, so no head or feet are cut.  A prediction that leaves
that frame (a diverged method, metres away) is *diverged*: it is clipped where it
leaves, its panel says "diverged: <mean error> cm", and it neither widens the view nor
sets the colour scale, which comes from the other panels.  Error colours are drawn
unlit (flat), so a pixel's colour is the colour bar's colour of its error; the ground
truth and the body are lit.  The PNG still is the *representative* frame
(:func:`representative_frame`): the frame whose mean error of the first predicted
panel is closest to that panel's median over the frames.

Rendering is pyvista/VTK off-screen (a real depth buffer, so the body never shows
through a garment drawn in front of it).  With no display it uses EGL
(``VTK_DEFAULT_OPENGL_WINDOW=vtkEGLRenderWindow``, set here unless already set; apt
``libegl1 libgl1-mesa-dri``).  Titles and the colour bar are drawn with
Pillow/matplotlib onto the rendered frames; imageio-ffmpeg writes the MP4.

Install: ``pip install "garmentgnn[viz]"`` (pyvista, vtk, imageio, imageio-ffmpeg).
"""
from __future__ import annotations

import ctypes.util
import functools
import os
import re
import subprocess
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Dict, List, Optional, Sequence, Tuple, Union

import numpy as np
import torch
from PIL import Image, ImageDraw, ImageFont

from garmentgnn._plotting import pyplot
from garmentgnn.geometry import vertex_normals

PathLike = Union[str, os.PathLike]
RGB = Tuple[float, float, float]

GT_COLOR: RGB = (0.30, 0.50, 0.78)
BODY_COLOR: RGB = (0.80, 0.80, 0.80)
_HEADER, _FOOTER = 80, 96  # px above (titles) and below (colour bar) the 3D panels
_INSTALL = ('pip install "garmentgnn[viz]"  (pyvista, vtk, imageio, imageio-ffmpeg) and, '
            "with no display, apt-get install libegl1 libgl1-mesa-dri")


def _np(a) -> np.ndarray:
    if hasattr(a, "detach"):
        a = a.detach().cpu().numpy()
    return np.asarray(a)


@dataclass
class Panel:
    """One panel: a garment sequence ``positions [T, V, 3]`` (metres), its ``title``
    and, for predictions, ``error [T, V]`` per-vertex distance to the ground truth in
    cm (``None``: drawn in plain ``color``)."""

    title: str
    positions: np.ndarray
    error: Optional[np.ndarray] = None
    color: RGB = GT_COLOR

    def __post_init__(self) -> None:
        self.positions = _np(self.positions).astype(np.float64)
        if self.positions.ndim != 3 or self.positions.shape[2] != 3:
            raise ValueError(f"Panel {self.title!r}: `positions` must be [T, V, 3], "
                             f"got {self.positions.shape}")
        if not np.isfinite(self.positions).all():
            raise ValueError(f"Panel {self.title!r}: `positions` contain NaN/inf")
        if self.error is not None:
            self.error = _np(self.error).astype(np.float64)
            if self.error.shape != self.positions.shape[:2]:
                raise ValueError(f"Panel {self.title!r}: `error` must be [T, V] = "
                                 f"{self.positions.shape[:2]}, got {self.error.shape}")
            if not np.isfinite(self.error).all():
                raise ValueError(f"Panel {self.title!r}: `error` contains NaN/inf")

    def __repr__(self) -> str:
        T, V, _ = self.positions.shape
        return f"Panel({self.title!r}, frames={T}, vertices={V}, error={self.error is not None})"


def vertex_error_cm(pred, gt) -> np.ndarray:
    """``[T, V]`` per-vertex Euclidean distance between ``pred`` and ``gt`` (metres in,
    cm out): the per-vertex term of the ``E_dist`` metric."""
    p, g = _np(pred).astype(np.float64), _np(gt).astype(np.float64)
    if p.shape != g.shape or p.ndim != 3 or p.shape[-1] != 3:
        raise ValueError(f"`pred` and `gt` must both be [T, V, 3], got {p.shape} and {g.shape}")
    return 100.0 * np.linalg.norm(p - g, axis=-1)


_PROBE = """
import os
os.environ.setdefault("VTK_DEFAULT_OPENGL_WINDOW", "vtkEGLRenderWindow")
import pyvista
p = pyvista.Plotter(off_screen=True, window_size=(16, 16))
p.add_mesh(pyvista.Sphere())
assert p.screenshot(return_img=True).shape == (16, 16, 3)
p.close()
"""


@functools.lru_cache(maxsize=None)
def renderer_unavailable(probe: bool = True) -> Optional[str]:
    """``None`` if off-screen rendering works here, otherwise why not (and how to fix).

    With ``probe`` (default) a tiny render runs once in a subprocess: VTK segfaults
    instead of raising when the GL libraries are incomplete (e.g. ``libegl1`` without
    ``libgl1-mesa-dri``), and that must not take the calling process down."""
    try:  # the viz extra's optional packages, imported only to see that they are there
        import imageio  # noqa: F401, PLC0415
        import imageio_ffmpeg  # noqa: F401, PLC0415
        import pyvista  # noqa: F401, PLC0415
    except ImportError as e:
        return f"{e.name} is not installed: {_INSTALL}"
    if not os.environ.get("DISPLAY") and ctypes.util.find_library("EGL") is None:
        return f"no display and no libEGL: {_INSTALL}"
    if probe:
        try:
            r = subprocess.run([sys.executable, "-c", _PROBE], capture_output=True, text=True,
                               timeout=120)
        except subprocess.TimeoutExpired:
            return f"a 16x16 test render timed out: {_INSTALL}"
        if r.returncode != 0:
            text = re.sub(r"\x1b\[[0-9;]*m", "", r.stderr or r.stdout).strip()
            tail = text.splitlines()[-1:] or [f"exit {r.returncode}"]
            return f"a 16x16 test render failed ({tail[0][:200]}): {_INSTALL}"
    return None


def _pyvista():
    os.environ.setdefault("VTK_DEFAULT_OPENGL_WINDOW", "vtkEGLRenderWindow")
    reason = renderer_unavailable(probe=False)
    if reason:
        raise ImportError(reason)
    import pyvista  # noqa: PLC0415 (optional: the viz extra)
    return pyvista


def _normals(points: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Area-weighted unit vertex normals ``[V, 3]`` (smooth shading of a moving mesh)."""
    return vertex_normals(torch.from_numpy(points), torch.from_numpy(faces)).numpy()


def _font(size: int):
    from matplotlib import font_manager  # noqa: PLC0415 (matplotlib: loaded on the first figure)
    return ImageFont.truetype(font_manager.findfont("DejaVu Sans"), size)


def default_error_limit(errors: Sequence[np.ndarray]) -> float:
    """Top of the default error colour range (cm): the median over the panels of each
    panel's 99th-percentile error.  One diverged panel (a method metres off) then
    saturates at the colour bar's arrow instead of washing every other panel out to the
    bottom colour; 1.0 without errors."""
    if not errors:
        return 1.0
    return float(np.median([np.percentile(np.asarray(e).ravel(), 99) for e in errors]))


def representative_frame(error: np.ndarray) -> int:
    """The frame (``error [T, V]``) whose mean error is closest to the median of the
    per-frame means: a still that shows a typical frame, not a lucky or unlucky one
    (the first such frame on ties)."""
    per_frame = np.asarray(error, np.float64).reshape(len(error), -1).mean(1)
    return int(np.argmin(np.abs(per_frame - np.median(per_frame))))


def _view_axes(elev: float, azim: float) -> Tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(towards the camera, screen right, screen up) unit vectors, Z up."""
    e, a = np.radians(elev), np.radians(azim)
    back = np.array([np.cos(e) * np.cos(a), np.cos(e) * np.sin(a), np.sin(e)])
    right = np.cross(-back, [0.0, 0.0, 1.0])
    right /= np.linalg.norm(right)
    return back, right, np.cross(right, -back)


@dataclass
class View:
    """A parallel-projection camera (:func:`frame_view`): ``focal`` point, ``half_height``
    (VTK's parallel scale, metres), ``aspect`` (width / height of the framed extent) and
    ``outside [panels, T]``: the fraction of each panel's garment vertices outside the
    frame per frame; ``diverged`` panels are those that leave it."""

    focal: np.ndarray
    back: np.ndarray
    half_height: float
    aspect: float
    outside: np.ndarray
    diverged: List[int]

    def camera(self) -> Tuple[np.ndarray, np.ndarray]:
        """(position, focal point)."""
        return self.focal + 10.0 * max(self.half_height, 0.1) * self.back, self.focal


def frame_view(panels: Sequence["Panel"], body: Optional[np.ndarray], elev: float,
               azim: float, margin: float = 0.04, tolerance: float = 0.1,
               leave: float = 0.01) -> View:
    """Frame the camera on the body (all frames) and the panels without an error (the
    ground truth), then on every predicted panel that stays within that frame widened
    by ``tolerance`` of its size on each side (at most ``leave`` of its vertices outside
    in every frame); the others are diverged.  ``margin``: blank border (fraction)."""
    back, right, up = _view_axes(elev, azim)

    def uv(points: np.ndarray) -> np.ndarray:
        return np.stack([points @ right, points @ up], -1)

    ref = [p.positions.reshape(-1, 3) for p in panels if p.error is None] or \
        [panels[0].positions.reshape(-1, 3)]
    if body is not None:
        ref.append(body.reshape(-1, 3))
    r = uv(np.concatenate(ref))
    lo, hi = r.min(0), r.max(0)
    pad = tolerance * (hi - lo).max()
    outside = np.zeros((len(panels), panels[0].positions.shape[0]))
    for j, p in enumerate(panels):
        q = uv(p.positions)  # [T, V, 2]
        out = ((q < lo - pad) | (q > hi + pad)).any(-1)
        outside[j] = out.mean(1)
    diverged = [j for j, p in enumerate(panels)
                if p.error is not None and outside[j].max() > leave]
    keep = [uv(p.positions.reshape(-1, 3)) for j, p in enumerate(panels) if j not in diverged]
    pts = np.concatenate([r] + keep)
    lo, hi = pts.min(0), pts.max(0)
    size = np.maximum(hi - lo, 1e-3) * (1 + 2 * margin)
    mid = (lo + hi) / 2
    centre = np.concatenate([p.positions.reshape(-1, 3) for p in panels]).mean(0)
    focal = centre + right * (mid[0] - centre @ right) + up * (mid[1] - centre @ up)
    return View(focal, back, float(size[1] / 2), float(size[0] / size[1]), outside, diverged)


def colorbar_image(width: int, height: int, clim: Tuple[float, float], cmap: str,
                   label: str) -> np.ndarray:
    """``[height, width, 3]`` uint8: a horizontal matplotlib colour bar."""
    plt = pyplot()

    dpi = 100
    fig = plt.figure(figsize=(width / dpi, height / dpi), dpi=dpi)
    ax = fig.add_axes((0.04, 0.52, 0.92, 0.22))
    cb = fig.colorbar(plt.cm.ScalarMappable(plt.Normalize(*clim), cmap), cax=ax,
                      orientation="horizontal", extend="max")
    cb.set_label(label, fontsize=13)
    cb.ax.tick_params(labelsize=12)
    cb.ax.xaxis.set_label_position("top")
    fig.canvas.draw()
    img = np.asarray(fig.canvas.buffer_rgba())[..., :3].copy()
    plt.close(fig)
    return img


@dataclass
class Animation:
    """What :func:`render_animation` wrote, and how long it took."""

    mp4: Optional[Path]
    gif: Optional[Path]
    still: Path
    frames: int
    size: Tuple[int, int]  # (width, height) of a frame
    fps: float
    clim: Tuple[float, float]
    seconds: float
    mean_error: Dict[str, float] = field(default_factory=dict)  # cm, per predicted panel
    still_frame: int = 0  # the frame of the PNG (0-based, within the panels' frames)
    still_error: Dict[str, float] = field(default_factory=dict)  # cm, on that frame
    diverged: List[str] = field(default_factory=list)  # panels that left the frame


def _round_up(x: float, m: int = 16) -> int:
    return int(-(-int(round(x)) // m) * m)


def render_animation(panels: Sequence[Panel], faces, out: PathLike,
                     body_positions=None, body_faces=None, *, fps: float = 30.0,
                     min_seconds: float = 3.0, height: int = 896, panel_width: Optional[int] = None,
                     clim: Optional[Tuple[float, float]] = None, cmap: str = "YlOrRd",
                     elev: float = 10.0, azim: float = -70.0, mp4: bool = True,
                     gif: bool = True, gif_scale: float = 0.5, still_frame: Optional[int] = None,
                     caption: str = "", frame_offset: int = 0) -> Animation:
    """Render ``panels`` side by side over their frames and write
    ``<out>.mp4``, ``<out>.gif`` and ``<out>.png`` (one still frame).

    Args:
        panels: same frame count ``T`` and vertex count in every panel.
        faces: ``[F, 3]`` garment triangles (shared by the panels, our vertex order).
        out: path without suffix (the suffixes are added).
        body_positions, body_faces: ``[T, Vb, 3]`` posed body and ``[Fb, 3]``, drawn in
            every panel (optional).
        fps: frame rate of the sequence; playback is slowed so the clip lasts at least
            ``min_seconds`` (short sequences), and the caption says so.
        height: frame height in px (>= 720; 3D area = height - 176 px of titles/colour bar).
        panel_width: px per panel (default: the framed view's aspect, between 0.45 and
            1.2 times the 3D height, rounded to 16).
        clim: colour range of the error in cm, shared by every panel (default: 0 ..
            :func:`default_error_limit` of the panels that did not diverge).
        elev, azim: camera elevation / azimuth in degrees (Z up; azimuth -90 looks at
            the front of a body facing -Y); one camera for every panel and frame,
            framed by :func:`frame_view`.
        gif_scale: GIF frames are this fraction of the MP4 size (file size).
        still_frame: which frame goes to the PNG (default: :func:`representative_frame`
            of the first predicted panel; the middle frame without one).
        caption: extra text under the colour bar (e.g. the sequence id).
        frame_offset: added to the frame numbers shown (when ``panels`` hold a slice).
    """
    if not panels:
        raise ValueError("`panels`: need at least one panel")
    T, V = panels[0].positions.shape[:2]
    for p in panels:
        if p.positions.shape[:2] != (T, V):
            raise ValueError(f"`panels`: {p!r} has [T, V] = {p.positions.shape[:2]}, the first "
                             f"panel has {(T, V)}; every panel must show the same frames")
    F = _np(faces).astype(np.int64)
    if F.ndim != 2 or F.shape[1] != 3 or F.min() < 0 or F.max() >= V:
        raise ValueError(f"`faces`: expected [F, 3] indices into {V} vertices")
    if height < 720:
        raise ValueError(f"`height`: expected >= 720 px, got {height}")
    if (body_positions is None) != (body_faces is None):
        raise ValueError("`body_positions` and `body_faces` go together")
    body = None
    if body_positions is not None:
        body = _np(body_positions).astype(np.float64)
        BF = _np(body_faces).astype(np.int64)
        if body.ndim != 3 or body.shape[0] != T:
            raise ValueError(f"`body_positions`: expected [T={T}, Vb, 3], got {body.shape}")
    pv = _pyvista()
    import imageio.v2 as imageio  # noqa: PLC0415 (optional: the viz extra)
    t_start = time.perf_counter()

    view = frame_view(panels, body, elev, azim)
    errs = [p.error for p in panels if p.error is not None]
    if clim is None:
        top = default_error_limit([p.error for j, p in enumerate(panels)
                                   if p.error is not None and j not in view.diverged] or errs)
        clim = (0.0, float(f"{max(top, 1e-3):.2g}"))
    elif not (len(clim) == 2 and np.isfinite(clim).all() and clim[1] > clim[0]):
        raise ValueError(f"`clim`: expected (low, high) in cm with high > low, got {clim}")
    h3d = _round_up(height - _HEADER - _FOOTER)
    H = h3d + _HEADER + _FOOTER
    pw = panel_width or _round_up(min(max(view.aspect, 0.45), 1.2) * h3d)
    n = len(panels)
    W = pw * n
    # one camera for everything, fitted to the body and ground truth (frame_view)
    half_h = view.half_height * max(1.0, view.aspect * h3d / pw)
    cam_pos, focal = view.camera()

    plotter = pv.Plotter(shape=(1, n), off_screen=True, window_size=(W, h3d), border=False)
    meshes = []
    for j, p in enumerate(panels):
        plotter.subplot(0, j)
        plotter.set_background("white")
        gm = pv.PolyData.from_regular_faces(p.positions[0].copy(), F)
        gm.point_data["Normals"] = _normals(p.positions[0], F)
        gm.point_data.active_normals_name = "Normals"
        kw = dict(smooth_shading=False, specular=0.15, diffuse=0.85, ambient=0.15)
        if p.error is not None:  # unlit: every pixel is a colour of the colour bar
            gm.point_data["err"] = p.error[0].copy()
            plotter.add_mesh(gm, scalars="err", cmap=cmap, clim=clim, show_scalar_bar=False,
                             lighting=False)
        else:
            plotter.add_mesh(gm, color=p.color, **kw)
        bm = None
        if body is not None:
            bm = pv.PolyData.from_regular_faces(body[0].copy(), BF)
            bm.point_data["Normals"] = _normals(body[0], BF)
            bm.point_data.active_normals_name = "Normals"
            plotter.add_mesh(bm, color=BODY_COLOR, smooth_shading=False, specular=0.05)
        cam = plotter.camera
        cam.position, cam.focal_point, cam.up = tuple(cam_pos), tuple(focal), (0, 0, 1)
        cam.parallel_projection = True
        cam.parallel_scale = half_h
        meshes.append((p, gm, bm))

    slow = max(1.0, min_seconds * fps / T) if T > 1 else 1.0
    play_fps = fps / slow
    font_s = _font(20)
    size = 30  # one title size for every panel: the largest at which all of them fit
    while size > 12 and max(_font(size).getlength(p.title) for p in panels) > pw - 16:
        size -= 2
    title_font = _font(size)
    info_size = 20
    while info_size > 11 and _font(info_size).getlength("mean 00.00 cm, max 000.0") > pw - 12:
        info_size -= 1
    font_info = _font(info_size)
    bar = colorbar_image(min(W - 40, 900), _FOOTER - 24, clim, cmap,
                         "distance to ground truth, E_dist (cm)") if errs else None
    mean_err = {p.title: float(p.error.mean()) for p in panels if p.error is not None}

    def compose(img3d: np.ndarray, t: int) -> np.ndarray:
        canvas = Image.new("RGB", (W, H), "white")
        canvas.paste(Image.fromarray(img3d), (0, _HEADER))
        d = ImageDraw.Draw(canvas)
        for j, p in enumerate(panels):
            cx = j * pw + pw // 2
            d.text((cx, 8), p.title, fill="black", font=title_font, anchor="ma")
            if p.error is not None and view.outside[j, t] > 0.01:
                d.text((cx, 46), f"diverged: {p.error[t].mean():.0f} cm",
                       fill=(180, 0, 0), font=font_info, anchor="ma")
            elif p.error is not None:
                d.text((cx, 46), f"mean {p.error[t].mean():.2f} cm, max {p.error[t].max():.1f}",
                       fill=(70, 70, 70), font=font_info, anchor="ma")
            if j:
                d.line([(j * pw, _HEADER), (j * pw, _HEADER + h3d)], fill=(200, 200, 200), width=2)
        if bar is not None:
            canvas.paste(Image.fromarray(bar), ((W - bar.shape[1]) // 2, _HEADER + h3d + 4))
        info = f"frame {t + frame_offset + 1} / {T + frame_offset}"
        if slow > 1.0:
            info += f"  (playing {slow:.3g}x slower)"
        d.text((10, H - 8), info, fill=(70, 70, 70), font=font_s, anchor="ld")
        if caption:
            d.text((W - 10, H - 8), caption, fill=(70, 70, 70), font=font_s, anchor="rd")
        return np.asarray(canvas)

    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    mp4_path = out.with_suffix(".mp4") if mp4 else None
    gif_path = out.with_suffix(".gif") if gif else None
    still_path = out.with_suffix(".png")
    if still_frame is None:
        still_frame = representative_frame(errs[0]) if errs else T // 2
    still_frame = int(still_frame)
    if not 0 <= still_frame < T:
        raise ValueError(f"`still_frame`: expected 0 <= still_frame < {T}, got {still_frame}")
    writer = (imageio.get_writer(mp4_path, fps=play_fps, codec="libx264", quality=7,
                                 macro_block_size=16, pixelformat="yuv420p",
                                 ffmpeg_log_level="error")
              if mp4_path else None)
    gif_frames: List[np.ndarray] = []
    try:
        for t in range(T):
            for p, gm, bm in meshes:
                gm.points[:] = p.positions[t]
                gm.point_data["Normals"][:] = _normals(p.positions[t], F)
                if p.error is not None:
                    gm.point_data["err"][:] = p.error[t]
                gm.Modified()
                if bm is not None:
                    bm.points[:] = body[t]
                    bm.point_data["Normals"][:] = _normals(body[t], BF)
                    bm.Modified()
            plotter.render()
            frame = compose(plotter.screenshot(return_img=True), t)
            if writer is not None:
                writer.append_data(frame)
            if gif_path is not None:
                small = Image.fromarray(frame).resize(
                    (_round_up(W * gif_scale, 2), _round_up(H * gif_scale, 2)), Image.LANCZOS)
                gif_frames.append(np.asarray(small))
            if t == still_frame:
                Image.fromarray(frame).save(still_path)
    finally:
        if writer is not None:
            writer.close()
        plotter.close()
    if gif_path is not None:
        import imageio.v3 as iio  # noqa: PLC0415 (optional: the viz extra)
        iio.imwrite(gif_path, np.stack(gif_frames), duration=1000.0 / play_fps, loop=0)
    return Animation(mp4=mp4_path, gif=gif_path, still=still_path, frames=T, size=(W, H),
                     fps=play_fps, clim=tuple(clim), seconds=time.perf_counter() - t_start,
                     mean_error=mean_err, still_frame=still_frame,
                     still_error={p.title: float(p.error[still_frame].mean())
                                  for p in panels if p.error is not None},
                     diverged=[panels[j].title for j in view.diverged])

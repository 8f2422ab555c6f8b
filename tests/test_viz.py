"""Side-by-side animations: what the frames show (panel colours from the colour map,
motion between frames), the files (MP4 and GIF read back by imageio), the error
against the metric, the comparison of checkpoints and ``garmentgnn show``."""
import lightning as L
import matplotlib
import numpy as np
import pytest
import torch
import trimesh
from PIL import Image
from trimesh.transformations import rotation_matrix

from garmentgnn._plotting import pyplot
from garmentgnn.cli import main
from garmentgnn.data import store
from garmentgnn.metrics import vertex_distance
from garmentgnn.training import GarTransModule, GarmentDataModule
from garmentgnn.training.evaluate import evaluate_split
from garmentgnn.viz.animate import (Panel, _FOOTER, _HEADER, default_error_limit, render_animation,
                                    renderer_unavailable, vertex_error_cm)
from garmentgnn.viz.compare import comparison
from garmentgnn.viz.viewer import bundle_path
from garmentgnn.models import GarTrans

from test_viz_export import dataset  # noqa: F401  (module-scoped toy dataset)

REASON = renderer_unavailable()
needs_renderer = pytest.mark.skipif(REASON is not None, reason=f"no off-screen renderer: {REASON}")


def test_vertex_error_matches_the_metric():
    g = torch.Generator().manual_seed(0)
    gt, pred = torch.randn(4, 30, 3, generator=g), torch.randn(4, 30, 3, generator=g)
    e = vertex_error_cm(pred, gt)
    assert e.shape == (4, 30)
    np.testing.assert_allclose(e.mean(1), vertex_distance(pred, gt).numpy(), rtol=1e-6)
    with pytest.raises(ValueError, match="pred"):
        vertex_error_cm(pred[:, :5], gt)


def test_default_error_limit_ignores_one_diverged_panel():
    ramp = np.linspace(0.0, 10.0, 1001)  # 99th percentile: 9.9 cm exactly
    assert default_error_limit([ramp]) == pytest.approx(9.9)
    # three close methods and one 200 cm off: the median panel sets the range, not the
    # outlier (a pooled percentile would give ~200 cm and a uniformly pale picture)
    errs = [ramp, ramp * 1.1, ramp * 0.9, ramp + 200.0]
    assert default_error_limit(errs) == pytest.approx(np.median([9.9, 10.89, 8.91, 209.9]))
    assert default_error_limit([]) == 1.0


def test_panel_checks_its_input():
    with pytest.raises(ValueError, match="positions"):
        Panel("a", np.zeros((3, 4)))
    with pytest.raises(ValueError, match="NaN"):
        Panel("a", np.full((2, 4, 3), np.nan))
    with pytest.raises(ValueError, match="error"):
        Panel("a", np.zeros((2, 4, 3)), np.zeros((2, 5)))


def scene(T=3):
    """A sphere 'body' and an open tube 'garment' around it moving along x."""
    body = trimesh.creation.icosphere(subdivisions=2, radius=0.10)
    tube = trimesh.creation.cylinder(radius=0.15, height=0.30, sections=24)
    shift = np.array([0.04, 0.0, 0.0])
    G = np.stack([tube.vertices + t * shift for t in range(T)])
    B = np.stack([body.vertices + t * shift for t in range(T)])
    return G, tube.faces, B, body.faces


@needs_renderer
def test_render_animation_frames_and_files(tmp_path):
    import imageio.v2 as imageio  # noqa: PLC0415 (optional: the viz extra)
    import imageio.v3 as iio  # noqa: PLC0415 (optional: the viz extra)
    G, F, B, BF = scene()
    T, V = G.shape[:2]
    panels = [Panel("truth", G), Panel("exact", G, np.zeros((T, V))),
              Panel("far", G + 0.05, np.full((T, V), 5.0))]
    a = render_animation(panels, F, tmp_path / "anim", B, BF, fps=30, min_seconds=0.0,
                         height=720, panel_width=224, clim=(0.0, 5.0))
    W, H = a.size
    assert (W, H) == (3 * 224, 720) and a.frames == T and a.clim == (0.0, 5.0)
    assert a.mean_error == {"exact": 0.0, "far": 5.0}
    still = iio.imread(a.still)
    assert still.shape[:2] == (720, W)
    h3d = H - _HEADER - _FOOTER
    px = still[_HEADER:_HEADER + h3d, :, :3].astype(int)
    r, g, b = px[..., 0], px[..., 1], px[..., 2]
    blue = (b > r + 40).reshape(h3d, 3, 224).mean(axis=(0, 2))
    red = ((r > 2 * g) & (r > 2 * b) & (r > 60)).reshape(h3d, 3, 224).mean(axis=(0, 2))
    # truth in plain blue; zero error = the colour map's pale low end; 5 cm = its dark red
    assert blue[0] > 0.02 and blue[1] < 1e-3 and blue[2] < 1e-3
    assert red[2] > 0.02 and red[1] < 1e-3 and red[0] < 1e-3
    # the MP4 and the GIF hold every frame, and the garment moves between frames
    rd = imageio.get_reader(a.mp4)
    video = [f for f in rd]
    rd.close()
    assert len(video) == T and video[0].shape == (H, W, 3)
    assert np.abs(video[0].astype(int) - video[-1].astype(int)).max(-1).__gt__(40).mean() > 0.005
    gif = iio.imread(a.gif, index=None)
    assert gif.shape[0] == T and gif.shape[1] == H // 2
    with pytest.raises(ValueError, match="clim"):
        render_animation(panels, F, tmp_path / "x", clim=(2.0, 2.0))
    with pytest.raises(ValueError, match="height"):
        render_animation(panels, F, tmp_path / "x", height=480)
    with pytest.raises(ValueError, match="same frames"):
        render_animation([panels[0], Panel("short", G[:2])], F, tmp_path / "x")


def person(T=3):
    """A 1.9 m 'body' (legs, torso, head, raised arms) and a 1 m long dress-like frustum
    around it, swaying along x."""
    parts = [trimesh.creation.cylinder(radius=0.06, height=0.8, sections=12)
             .apply_translation([x, 0, 0.4]) for x in (-0.1, 0.1)]
    parts.append(trimesh.creation.cylinder(radius=0.16, height=0.65, sections=16)
                 .apply_translation([0, 0, 1.125]))
    parts.append(trimesh.creation.icosphere(2, radius=0.11).apply_translation([0, 0, 1.58]))
    for sx in (-1, 1):
        arm = trimesh.creation.cylinder(radius=0.045, height=0.6, sections=10)
        parts.append(arm.apply_transform(rotation_matrix(sx * 0.6, [0, 1, 0]))
                     .apply_translation([sx * 0.32, 0, 1.6]))
    body = trimesh.util.concatenate(parts)
    dress = trimesh.creation.cylinder(radius=1.0, height=1.0, sections=32)
    V = dress.vertices.copy()
    V[:, :2] *= np.where(V[:, 2:] > 0, 0.2, 0.34)  # narrow at the top (z 1.45), wide below
    V[:, 2] += 0.95
    sway = np.array([0.03, 0.0, 0.0])
    return (np.stack([V + t * sway for t in range(T)]), dress.faces,
            np.stack([body.vertices + t * sway for t in range(T)]), body.faces)


@needs_renderer
def test_render_frames_the_body_and_clips_a_diverged_panel(tmp_path):
    """One prediction falls metres away: the others are still framed on the body (the
    old shared camera followed the diverged garment and left each other garment a
    quarter of its panel), the diverged one is labelled, and the colour scale comes
    from the panels that stayed."""
    import imageio.v3 as iio  # noqa: PLC0415 (optional: the viz extra)
    G, F, B, BF = person()
    T = G.shape[0]
    rng = np.random.default_rng(0)
    far = G + np.linspace(0.3, 2.4, T)[:, None, None] * np.array([0.3, -0.2, -1.0])
    preds = {"GarTrans": G + rng.normal(0, 0.01, G.shape), "HOOD-style": far,
             "LBS only": G * np.array([1.04, 1.04, 1.0])}
    panels = [Panel("simulated (ground truth)", G)] + [
        Panel(k, P, vertex_error_cm(P, G)) for k, P in preds.items()]
    a = render_animation(panels, F, tmp_path / "a", B, BF, fps=30, min_seconds=0.0,
                         height=720, mp4=False, gif=False, still_frame=T - 1)
    assert a.diverged == ["HOOD-style"]
    stayed = [p.error for p in panels[1:] if p.title != "HOOD-style"]
    assert a.clim[1] < 5.0 < np.percentile(panels[2].error, 1)  # not set by HOOD-style
    assert a.clim[1] >= 0.9 * min(np.percentile(e, 99) for e in stayed)
    W, H = a.size
    h3d = H - _HEADER - _FOOTER
    pw = W // len(panels)
    px = iio.imread(a.still)[_HEADER:_HEADER + h3d, :, :3].astype(int)
    chroma = px.max(-1) - px.min(-1)
    garment = chroma > 30  # the blue truth and the colour map; body grey, background white
    grey = (chroma < 12) & (px.max(-1) < 235)
    for j, p in enumerate(panels):
        rows = np.flatnonzero(garment[:, j * pw:(j + 1) * pw].sum(1) >= 3)
        body_rows = np.flatnonzero(grey[:, j * pw + 4:(j + 1) * pw - 4].sum(1) >= 3)
        # the whole body is in frame: neither its head nor its feet touch the edges
        assert body_rows.min() > 2 and body_rows.max() < h3d - 3, p.title
        if p.title == "HOOD-style":
            assert len(rows) == 0  # left the frame (clipped), said in the panel's label
            continue
        assert (rows.max() - rows.min() + 1) / h3d >= 0.4, p.title


def test_comparison_against_evaluate_split(dataset, tmp_path):  # noqa: F811
    dm = GarmentDataModule(dataset, chunk=4, history=2, nystrom_dim=8, num_landmarks=16,
                           val_split=None)
    module = GarTransModule(GarTrans(**dm.model_sizes(GarTrans)))
    c = comparison(dataset, {"GarTrans": module}, split="test", history=2, num_landmarks=16)
    assert [p.title for p in c.panels] == ["simulated (ground truth)", "GarTrans", "LBS only"]
    rec = [r for r in store.read_manifest(dataset)["items"] if r["split"] == "test"][0]
    np.testing.assert_allclose(c.panels[0].positions,
                               store.load_sequence(store.sequence_path(dataset, rec))["positions"],
                               atol=1e-6)
    ref = evaluate_split(module, dataset, "test", modes=("gartrans",), history=2,
                         num_landmarks=16)  # the model on the same inputs as the evaluation
    assert c.panels[1].error.mean() == pytest.approx(ref["gartrans"]["E_dist"], rel=1e-4)
    lbs_ref = vertex_distance(torch.from_numpy(c.panels[2].positions),
                              torch.from_numpy(c.panels[0].positions))
    np.testing.assert_allclose(c.panels[2].error.mean(1), lbs_ref.numpy(), rtol=1e-6)
    assert c.panels[2].error.mean() > 0.01  # LBS differs from the simulation
    assert c.body_positions.shape[0] == c.panels[0].positions.shape[0]
    with pytest.raises(ValueError, match="index"):
        comparison(dataset, {}, split="test", index=5, history=2, num_landmarks=16)
    with pytest.raises(FileNotFoundError):
        comparison(dataset, {"x": tmp_path / "missing.ckpt"}, split="test")


@needs_renderer
def test_show_cli_from_a_checkpoint(dataset, tmp_path, capsys):  # noqa: F811
    dm = GarmentDataModule(dataset, chunk=4, history=2, nystrom_dim=8, num_landmarks=16,
                           val_split=None)
    module = GarTransModule(GarTrans(**dm.model_sizes(GarTrans)))
    trainer = L.Trainer(max_epochs=0, logger=False, enable_checkpointing=False,
                        enable_progress_bar=False, enable_model_summary=False,
                        default_root_dir=str(tmp_path))
    trainer.fit(module, dm)
    ckpt = tmp_path / "m.ckpt"
    trainer.save_checkpoint(ckpt)
    # a precomputed prediction: the simulation moved 1 cm along x, so exactly 1 cm off
    rec = [r for r in store.read_manifest(dataset)["items"] if r["split"] == "test"][0]
    gt = store.load_sequence(store.sequence_path(dataset, rec))["positions"]
    np.save(tmp_path / "shifted.npy", gt + np.array([0.01, 0.0, 0.0], np.float32))
    out = tmp_path / "show" / "cmp"
    viewer = bundle_path().is_file()
    capsys.readouterr()
    assert main(["show", "--data", str(dataset), "--ckpt", f"mine={ckpt}", "--out", str(out),
                 "--pred", f"shifted={tmp_path / 'shifted.npy'}",
                 "--history", "2", "--num-landmarks", "16", "--max-frames", "2",
                 "--height", "720", "--no-gif"] + (["--html"] if viewer else [])) == 0
    printed = capsys.readouterr().out
    assert "shifted: mean E_dist 1.000 cm" in printed and "LBS only: mean E_dist" in printed
    # the still's frame and its numbers: 1 cm on every frame
    assert "the frame closest to the first prediction's median per-frame error" in printed
    assert out.with_suffix(".html").is_file() == viewer
    if viewer:
        assert f"wrote {out.with_suffix('.html')}" in printed
    assert Image.open(out.with_suffix(".png")).size[1] >= 720
    assert out.with_suffix(".mp4").stat().st_size > 1000 and not out.with_suffix(".gif").exists()
    assert out.with_suffix(".png").is_file() and out.with_suffix(".glb").is_file()


def test_plots_draw_on_the_off_screen_backend_whatever_was_selected():
    matplotlib.use("svg")
    assert pyplot().get_backend().lower() == "agg"

"""The single-file HTML viewer, opened in headless Chromium: the exported glTF renders
(a screenshot that is not blank, the garment's colour on screen) and animates
(frames at two times differ); a comparison shows the error colours of the colour map
exactly (unlit), the panel labels and the colour bar; with WebGL off or a damaged file
the page says so in a visible box."""
import re
import shutil
import subprocess

import numpy as np
import pytest
import trimesh
from matplotlib import colormaps
from PIL import Image

from garmentgnn.data.gltf import GltfMesh, write_gltf
from garmentgnn.viz.animate import Panel, vertex_error_cm
from garmentgnn.viz.compare import Comparison, export_comparison_gltf
from garmentgnn.viz.viewer import bundle_path, write_viewer

CHROMIUM = next((shutil.which(n) for n in ("chromium", "chromium-headless-shell",
                                            "google-chrome") if shutil.which(n)), None)
pytest.importorskip("pygltflib", reason='pygltflib is not installed: pip install "garmentgnn[viz]"')


def _chromium(*args):
    return subprocess.run([CHROMIUM, "--headless", "--no-sandbox", "--enable-unsafe-swiftshader",
                           "--hide-scrollbars", "--virtual-time-budget=5000", *args],
                          check=True, capture_output=True, timeout=120, text=True).stdout


def screenshot(html, png, t, size=(480, 360), *flags):
    _chromium(*flags, f"--window-size={size[0]},{size[1]}", f"--screenshot={png}",
              f"file://{html}#t={t}")
    return np.asarray(Image.open(png).convert("RGB")).astype(int)


def dom(html, *flags):
    """The page's DOM after its scripts ran (``--dump-dom``)."""
    return _chromium(*flags, "--window-size=800,600", "--dump-dom", f"file://{html}")


needs_browser = [
    pytest.mark.skipif(CHROMIUM is None, reason="chromium is not installed (make install "
                       "installs it with apt; or apt-get install chromium)"),
    pytest.mark.skipif(not bundle_path().is_file(), reason=f"the viewer bundle "
                       f"{bundle_path()} is missing: make install builds it (npm)")]


def _status(page: str) -> str:
    m = re.search(r'<div id="status"( class="error")?>([^<]*)<', page)
    assert m, page[:500]
    return ("error: " if m.group(1) else "") + m.group(2)


@needs_browser[0]
@needs_browser[1]
def test_viewer_renders_and_animates_in_chromium(tmp_path):
    body = trimesh.creation.capsule(height=1.2, radius=0.15)  # Z up, like our bodies
    skirt = trimesh.creation.cylinder(radius=0.25, height=0.3, sections=32)
    T = 4
    G = np.stack([skirt.vertices + [0.25 * t, 0.0, 0.1] for t in range(T)])
    B = np.repeat(body.vertices[None], T, 0)
    glb = write_gltf(tmp_path / "s.glb", [GltfMesh("body", B, body.faces, (0.8, 0.8, 0.8)),
                                         GltfMesh("skirt", G, skirt.faces, (0.2, 0.4, 0.9))],
                     fps=4)
    html = write_viewer(glb, tmp_path / "s.html", title="test")
    a = screenshot(html, tmp_path / "a.png", 0.0)
    b = screenshot(html, tmp_path / "b.png", (T - 1) / 4)
    for img in (a, b):
        assert (img.min(-1) < 235).mean() > 0.01  # not blank
        r, g, bl = img[..., 0], img[..., 1], img[..., 2]
        assert ((bl > r + 50) & (bl > g + 20)).mean() > 0.003  # the blue skirt is drawn
    moved = (np.abs(a - b).max(-1) > 30).mean()
    assert moved > 0.003  # the morph-target animation moved it


def test_write_viewer_input_checks(tmp_path, monkeypatch):
    (tmp_path / "x.glb").write_bytes(b"not a glb")
    if bundle_path().is_file():
        with pytest.raises(ValueError, match="glb"):
            write_viewer(tmp_path / "x.glb", tmp_path / "x.html")
    monkeypatch.setenv("GARMENTGNN_VIEWER_BUNDLE", str(tmp_path / "missing.js"))
    with pytest.raises(FileNotFoundError, match="make install"):
        write_viewer(tmp_path / "x.glb", tmp_path / "x.html")


def _skirt_glb(path):
    skirt = trimesh.creation.cylinder(radius=0.25, height=0.3, sections=32)
    G = np.stack([skirt.vertices + [0.1 * t, 0.0, 0.0] for t in range(3)])
    return write_gltf(path, [GltfMesh("skirt", G, skirt.faces, (0.2, 0.4, 0.9))], fps=3)


@needs_browser[0]
@needs_browser[1]
def test_viewer_says_when_webgl_is_off(tmp_path):
    html = write_viewer(_skirt_glb(tmp_path / "s.glb"), tmp_path / "s.html")
    assert _status(dom(html)).startswith("s (drag")  # loaded: the title and a hint
    off = _status(dom(html, "--disable-3d-apis"))
    assert off.startswith("error: Cannot show the 3D view") and "WebGL" in off, off
    img = screenshot(html, tmp_path / "off.png", 0, (640, 480), "--disable-3d-apis")
    r, g, b = img[..., 0], img[..., 1], img[..., 2]
    assert ((r > 150) & (g < 60) & (b < 60)).mean() > 0.001  # the red box's border is drawn


@needs_browser[0]
@needs_browser[1]
def test_viewer_says_when_the_file_is_damaged(tmp_path):
    html = write_viewer(_skirt_glb(tmp_path / "s.glb"), tmp_path / "s.html")
    text = html.read_text()
    start = text.index('type="application/octet-stream">') + len('type="application/octet-stream">')
    damaged = tmp_path / "d.html"
    damaged.write_text(text[:start] + "Z2xURgIAAAAAAAAA" + text[text.index("</script>", start):])
    status = _status(dom(damaged))
    assert status.startswith("error: Could not read the glTF model"), status
    broken = tmp_path / "b.html"  # not base64 at all
    broken.write_text(text[:start] + "%%%" + text[text.index("</script>", start):])
    assert _status(dom(broken)).startswith("error: Could not load the model")


@pytest.mark.slow
@needs_browser[0]
@needs_browser[1]
def test_comparison_page_has_error_colours_labels_and_colour_bar(tmp_path):
    """A prediction 5 cm off everywhere on a 0-5 cm scale: on screen it has the colour
    map's top colour exactly (unlit, as in the MP4), next to the lit blue truth."""
    body = trimesh.creation.capsule(height=1.2, radius=0.15)
    skirt = trimesh.creation.cylinder(radius=0.25, height=0.3, sections=32)
    T = 3
    G = np.stack([skirt.vertices + [0.0, 0.0, 0.1]] * T)
    off = G + np.array([0.05, 0.0, 0.0])
    panels = [Panel("truth", G), Panel("shifted", off, vertex_error_cm(off, G))]
    c = Comparison("seq", panels, skirt.faces, np.stack([body.vertices] * T), body.faces,
                   30.0, np.arange(T))
    glb = export_comparison_gltf(c, tmp_path / "c.glb", clim=(0.0, 5.0))
    html = write_viewer(glb, tmp_path / "c.html", title="seq")
    page = dom(html)
    assert _status(page).startswith("seq")
    assert "shifted\nmean 5.00 cm" in page and ">truth<" in page
    assert "distance to ground truth" in page and "5+" in page
    img = screenshot(html, tmp_path / "c.png", 0.0, (640, 480))
    top = np.round(255 * np.array(colormaps["YlOrRd"](1.0)[:3])).astype(int)
    exact = (np.abs(img - top).max(-1) <= 3).mean()
    assert exact > 0.01, (top, exact)
    r, g, b = img[..., 0], img[..., 1], img[..., 2]
    assert ((b > r + 40) & (b > g + 10)).mean() > 0.003  # the blue truth

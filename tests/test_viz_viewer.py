"""The single-file HTML viewer, opened in headless Chromium: the exported glTF renders
(a screenshot that is not blank, the garment's colour on screen) and animates
(frames at two times differ)."""
import shutil
import subprocess

import numpy as np
import pytest

from garmentgnn.data.gltf import GltfMesh, write_gltf
from garmentgnn.viz.viewer import bundle_path, write_viewer

CHROMIUM = next((shutil.which(n) for n in ("chromium", "chromium-headless-shell",
                                            "google-chrome") if shutil.which(n)), None)
pytest.importorskip("pygltflib", reason='pygltflib is not installed: pip install "garmentgnn[viz]"')


def screenshot(html, png, t, size=(480, 360)):
    subprocess.run([CHROMIUM, "--headless", "--no-sandbox", "--enable-unsafe-swiftshader",
                    "--hide-scrollbars", f"--window-size={size[0]},{size[1]}",
                    "--virtual-time-budget=5000", f"--screenshot={png}",
                    f"file://{html}#t={t}"], check=True, capture_output=True, timeout=120)
    from PIL import Image
    return np.asarray(Image.open(png).convert("RGB")).astype(int)


@pytest.mark.skipif(CHROMIUM is None, reason="chromium is not installed (make install "
                    "installs it with apt; or apt-get install chromium)")
@pytest.mark.skipif(not bundle_path().is_file(), reason=f"the viewer bundle {bundle_path()} "
                    "is missing: make install builds it (npm)")
def test_viewer_renders_and_animates_in_chromium(tmp_path):
    import trimesh
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

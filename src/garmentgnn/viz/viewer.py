"""A single-file HTML viewer of an exported glTF: three.js plays the morph-target
animation, the mouse turns and zooms.

The page embeds the ``.glb`` (base64) and the three.js bundle, so it opens from
``file://`` with no server, no flags and no network.  The bundle
(``build/viewer/viewer.bundle.js``: ``viewer/viewer.js`` + three.js from npm, bundled by
esbuild) is built by ``make install``; by hand::

    mkdir -p build/viewer
    cp viewer/package.json viewer/package-lock.json viewer/viewer.js build/viewer/
    cd build/viewer && npm ci
    npx esbuild viewer.js --bundle --format=iife --minify --outfile=viewer.bundle.js

``GARMENTGNN_VIEWER_BUNDLE`` may point at a bundle elsewhere.
"""
from __future__ import annotations

import base64
import html
import json
import os
from pathlib import Path
from typing import Union

from garmentgnn._files import atomic_write_bytes

PathLike = Union[str, os.PathLike]

_REPO = Path(__file__).resolve().parents[3]
BUILD_HINT = ("build it with `make install` (needs npm), or by hand: mkdir -p build/viewer && "
              "cp viewer/package.json viewer/package-lock.json viewer/viewer.js build/viewer/ && "
              "cd build/viewer && npm ci && npx esbuild viewer.js --bundle --format=iife "
              "--minify --outfile=viewer.bundle.js")


def bundle_path() -> Path:
    """Where the three.js viewer bundle is expected."""
    env = os.environ.get("GARMENTGNN_VIEWER_BUNDLE")
    return Path(env) if env else _REPO / "build" / "viewer" / "viewer.bundle.js"


def viewer_bundle() -> str:
    """The three.js viewer bundle's text (:func:`bundle_path`), checked:
    ``FileNotFoundError`` when it is missing, ``ValueError`` when it is not the viewer's
    JavaScript (empty, not UTF-8 text, or without the page's ``glb`` element), each
    naming the file and how to rebuild it.  ``garmentgnn show --html`` calls it before
    it renders anything."""
    bundle = bundle_path()
    default = _REPO / "build" / "viewer" / "viewer.bundle.js"
    if os.environ.get("GARMENTGNN_VIEWER_BUNDLE"):
        # a path the user chose: named with the variable that chose it, and never to be
        # deleted (it may be any file, a dataset's too)
        name = f"the viewer bundle {bundle} (set by GARMENTGNN_VIEWER_BUNDLE)"
        fix = (f"point GARMENTGNN_VIEWER_BUNDLE at the viewer's bundle, or unset it to use "
               f"{default} ({BUILD_HINT})")
        missing = fix
    else:
        name, fix, missing = f"the viewer bundle {bundle}", f"delete it and {BUILD_HINT}", \
            BUILD_HINT
    if not bundle.is_file():
        raise FileNotFoundError(f"{name} is missing: {missing}")
    try:
        js = bundle.read_bytes().decode("utf-8")
    except UnicodeDecodeError as e:
        raise ValueError(f"{name} is not UTF-8 text (byte {e.start}): not the viewer's "
                         f"JavaScript; {fix}") from None
    if "glb" not in js:
        what = "empty" if not js.strip() else "not the viewer's JavaScript"
        raise ValueError(f"{name} is {what}; {fix}")
    return js


def write_viewer(glb: PathLike, out: PathLike, title: str = "") -> Path:
    """Write ``out`` (.html): one page that shows and plays ``glb``, with the labels and
    colour bar the file carries (:mod:`garmentgnn.data.gltf`); returns its path.  When
    WebGL is off or the file cannot be read, the page shows why in a red box.  The
    bundle is checked first (:func:`viewer_bundle`)."""
    js = viewer_bundle()
    data = Path(glb).read_bytes()
    if data[:4] != b"glTF":
        raise ValueError(f"`glb`: {glb} is not a binary glTF (.glb) file")
    js = js.replace("</script", "<\\/script")
    title = title or Path(glb).stem
    title_js = json.dumps(title).replace("<", "\\u003c")
    page = f"""<!DOCTYPE html>
<html lang="en"><head><meta charset="utf-8">
<meta name="viewport" content="width=device-width, initial-scale=1">
<title>{html.escape(title)}</title>
<style>html,body{{margin:0;height:100%;overflow:hidden;background:#fff;font:14px sans-serif}}
#status{{position:absolute;left:10px;top:8px;color:#333}}
#status.error{{left:50%;top:40%;transform:translateX(-50%);max-width:36em;padding:1em 1.4em;
color:#900;background:#fee;border:2px solid #c00;border-radius:6px;font-size:18px}}
.label{{position:absolute;transform:translate(-50%,-100%);white-space:pre;text-align:center;
font-size:15px;color:#222;pointer-events:none}}
#colorbar{{position:absolute;left:50%;bottom:10px;transform:translateX(-50%);width:min(60%,600px);
text-align:center;font-size:13px}}
#colorbar .ramp{{height:14px;border:1px solid #444}}
#colorbar .ticks{{display:flex;justify-content:space-between}}</style></head>
<body><div id="status">loading ...</div>
<script>window.__title = {title_js};
window.addEventListener("error", function (e) {{  // an error the viewer did not catch
  var d = document.getElementById("status");
  window.__error = String(e.message || e);
  if (d && !window.__ready) {{ d.textContent = "The viewer failed: " + window.__error;
    d.className = "error"; }}
}});</script>
<script id="glb" type="application/octet-stream">{base64.b64encode(data).decode()}</script>
<script>{js}</script>
</body></html>
"""
    return atomic_write_bytes(out, page.encode())

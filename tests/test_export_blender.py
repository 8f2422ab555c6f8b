"""The glTF export opens in Blender: its own importer (``bpy.ops.import_scene.gltf``, run
in the Blender engine's interpreter) reads every frame back, in our vertex order."""
import json
import subprocess

import numpy as np
import pytest

from garmentgnn.data import export, store
from garmentgnn.sim.blender import blender_available, find_blender_python
from test_viz_export import dataset  # noqa: F401  (the shared two-sequence toy dataset)

pytest.importorskip("pygltflib", reason="glTF export needs the viz extra")
pytestmark = pytest.mark.skipif(not blender_available(), reason="bpy not installed (make install)")

IMPORT = r'''
import bpy, json, sys
import numpy as np
bpy.ops.wm.read_factory_settings(use_empty=True)
bpy.ops.import_scene.gltf(filepath=sys.argv[1])
out = {}
for ob in bpy.data.objects:
    if ob.type != "MESH":
        continue
    me, M = ob.data, np.array(ob.matrix_world)
    frames = []
    for key in me.shape_keys.key_blocks[1:]:  # after "Basis": one per frame
        co = np.empty(len(me.vertices) * 3, np.float32)
        key.data.foreach_get("co", co)
        frames.append((co.reshape(-1, 3) @ M[:3, :3].T + M[:3, 3]).tolist())
    out[ob.name] = frames
json.dump(out, open(sys.argv[2], "w"))
'''


def test_gltf_sequence_opens_in_blender(dataset, tmp_path):  # noqa: F811
    seq_path = sorted((dataset / store.SEQUENCES).glob("*.npz"))[0]
    seq = store.load_sequence(seq_path)
    glb = export.export_sequence(seq_path, "gltf", tmp_path / "seq.glb")[0]
    script = tmp_path / "import.py"
    script.write_text(IMPORT)
    r = subprocess.run([find_blender_python(), str(script), str(glb), str(tmp_path / "o.json")],
                       capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stdout[-2000:] + r.stderr[-2000:]
    objects = json.loads((tmp_path / "o.json").read_text())
    P = seq["positions"]
    garment = [np.array(f) for name, f in objects.items() if len(f) and len(f[0]) == P.shape[1]]
    assert len(garment) == 1, {k: (len(v), len(v[0]) if v else 0) for k, v in objects.items()}
    G = np.stack(garment[0])
    assert G.shape == P.shape
    np.testing.assert_allclose(G, P, atol=1e-5)  # every frame, our vertex order, our axes

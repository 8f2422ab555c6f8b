"""Bad input to ``garmentgnn generate --spec`` and the readers behind it: each exact
input whose answer was unclear (a value converted unchecked, a YAML error without its
place, a repeated entry or a changed file not named, a Y-up garment told to translate)
now answered in one line naming the key or the file, and nothing written."""
import shutil

import numpy as np
import pytest
import trimesh

from garmentgnn.cli import main as cli_main
from garmentgnn.data import SequenceChunks, generate, store
from garmentgnn.data.spec_file import load_spec
from test_data import fake_simulate
from test_own_garment import GEN, files, one_error, write_spec  # noqa: F401 (a fixture)

WALK = "- {file: walk.bvh, scale: 0.01}"
CASES = {  # name: (motions, garments, extra spec text, words of the error line)
    "scale in words": (["- {file: walk.bvh, scale: cm}"], None, "",
                       ("spec.yaml", "`motions[0].scale`", "expected a number", "'cm'")),
    "negative start": (["- {file: walk.bvh, scale: 0.01, start: -2}"], None, "",
                       ("spec.yaml", "`motions[0].start`", "integer >= 0", "-2")),
    "mapping as a list": (["- {file: walk.bvh, scale: 0.01, mapping: [Hips, pelvis]}"], None,
                          "", ("`motions[0].mapping`", "expected a mapping of file joint",
                               "['Hips', 'pelvis']")),
    "repeated motion": ([WALK, WALK], None, "",
                        ("duplicate items", "motions[0] and motions[1]", "walk",
                         "give each entry once")),
    "repeated garment": ([WALK], ["- file: skirt.obj", "- file: skirt.obj"], "",
                         ("duplicate items", "garments[0] and garments[1]", "skirt")),
    "speed in words": (["- {generator: walk, speed: fast}"], None, "",
                       ("`motions[0].speed`", "expected a number", "'fast'")),
}


@pytest.mark.parametrize("case", list(CASES))
def test_spec_values_are_checked_naming_the_key(files, tmp_path, capsys, case):  # noqa: F811
    motions, garments, extra, words = CASES[case]
    spec = write_spec(files, motions=motions, garments=garments or ("- file: skirt.obj",),
                      extra=extra, name=f"spec-{case.replace(' ', '-')}.yaml")
    out = tmp_path / "out"
    words = tuple(w.replace("spec.yaml", spec.name) for w in words)
    one_error(capsys, cli_main(["generate", "--spec", str(spec), "--out", str(out)] + GEN),
              *words)
    assert not out.exists()


def test_malformed_yaml_keeps_its_line_and_column(files, tmp_path, capsys):  # noqa: F811
    spec = tmp_path / "bad.yaml"
    spec.write_text("name: mine\nframes: 5\nmotions:\n  - {file: walk.bvh, scale: 0.01\n"
                    "garments: [skirt.obj]\n")
    last = one_error(capsys, cli_main(["generate", "--spec", str(spec), "--out",
                                       str(tmp_path / "out")] + GEN),
                     "bad.yaml", "not readable YAML", "line 5, column 9")
    assert "expected ',' or '}'" in last


def test_a_mesh_changed_between_runs_is_named(files, tmp_path, capsys):  # noqa: F811
    """A garment edited after a first `generate --spec` was "a different dataset (spec
    'mine', seed 0)", without the file."""
    d = tmp_path / "in"
    shutil.copytree(files, d)
    spec = write_spec(d, motions=[WALK])
    out = tmp_path / "out"
    assert generate(load_spec(spec), out, workers=0, simulate_fn=fake_simulate,
                    progress=False).done == 1
    mesh = trimesh.load(d / "skirt.obj", process=False)
    mesh.vertices = np.asarray(mesh.vertices) * 1.001
    mesh.export(d / "skirt.obj")
    one_error(capsys, cli_main(["generate", "--spec", str(spec), "--out", str(out)] + GEN),
              str(out), "different dataset", f"{d / 'skirt.obj'} changed since it was made",
              "another --out")


def test_a_y_up_garment_is_told_to_rotate(files, tmp_path, capsys):  # noqa: F811
    d = tmp_path / "in"
    shutil.copytree(files, d)
    mesh = trimesh.load(d / "skirt.obj", process=False)
    v = np.asarray(mesh.vertices)
    mesh.vertices = np.stack([v[:, 0], v[:, 2], -v[:, 1]], 1)  # Z-up -> Y-up
    mesh.export(d / "yup.obj")
    spec = write_spec(d, garments=("- file: yup.obj",), motions=[WALK])
    last = one_error(capsys, cli_main(["generate", "--spec", str(spec), "--out",
                                       str(tmp_path / "out")] + GEN),
                     "yup.obj", "looks modelled Y-up", "rotate it +90 degrees about X")
    assert "translate it by" not in last  # rotated, it fits
    assert not (tmp_path / "out").exists()


def test_a_manifest_with_no_items_says_so(files, tmp_path):  # noqa: F811
    """A manifest listing no sequences answered "no 'train' split; name one that its
    manifest lists: " and an empty list."""
    (tmp_path / store.SEQUENCES).mkdir()
    store.atomic_write_json(tmp_path / store.MANIFEST, {"items": []})
    with pytest.raises(ValueError, match=r"manifest.json lists no sequences; simulate"):
        SequenceChunks(tmp_path, "train", chunk=4)

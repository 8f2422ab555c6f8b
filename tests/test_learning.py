"""Learning diagnostics and checkpoints: every active branch of every method gets a
gradient at step 0; defaults written once; checkpoints of earlier layouts load as trained."""
import inspect
import json
import runpy
import statistics
from pathlib import Path

import lightning as L
import numpy as np
import pytest
import torch
import yaml
from scipy.stats import wilcoxon
from torch_geometric.nn import Linear as PyGLinear

from garmentgnn.bench.methods import DA, GARTRANS, HOOD, NCS, RECIPES
from garmentgnn.data import store
from garmentgnn.models import GarTrans, PAPER_FORM
from garmentgnn.models.blocks import AttentionStack
from garmentgnn.models.inputs import GarmentInputs
from garmentgnn.physics.energies import GRAVITY
from garmentgnn.training import BaselineModule, GarmentDataModule, GarTransModule
from garmentgnn.training.recipes import recipe_path
from garmentgnn.training.diagnostics import branch_gradients, dead_branches
from garmentgnn.training.base import DATASET_KEY, dataset_stamp
from garmentgnn.training.integrity import CheckpointError, stamp_checkpoint
from garmentgnn.models.baselines import DAStyle, HOODStyle

from recipe_helpers import module as recipe_module
from test_training import NY, root  # noqa: F401  (the module-scoped toy dataset fixture)


DATA = {"chunk": 4, "history": 3, "nystrom_dim": NY, "num_landmarks": 16, "seed": 0}


@pytest.fixture(scope="module")
def dm(root):  # noqa: F811
    d = GarmentDataModule(root, **DATA)
    d.setup("fit")
    return d


def gartrans(dm, method="GarTrans (SAT)", **kw):
    return recipe_module(RECIPES[method], dm.root, DATA, **{f"model.model.{k}": v
                                                              for k, v in kw.items()})


@pytest.mark.parametrize("method", list(GARTRANS) + [DA, HOOD, NCS])
def test_every_branch_gets_a_gradient_at_step_0(dm, method):
    item = dm.train_set[1]
    if method in GARTRANS:
        module = gartrans(dm, method)
    else:  # NCS-style: the garment of the item's sequence alone
        data = dict(DATA, train_ids=[item.seq_id]) if method == NCS else DATA
        module = recipe_module(RECIPES[method], dm.root, data)
    rep = branch_gradients(module, item)
    assert rep and dead_branches(rep) == []
    assert all(r["with_grad"] == r["trainable"] for r in rep.values()), rep


def test_zero_gates_leave_the_gated_branches_without_gradient(dm):
    """The diagnostic finds what it is for: gates started at exactly 0 multiply every
    learned branch, so only the gates move at first."""
    rep = branch_gradients(gartrans(dm, gate_init=0.0), dm.train_set[1])
    assert set(dead_branches(rep)) == {"rest_fc", "rest_attn", "nystrom_fc", "body_fc", "gru",
                                       "gru_out", "dynamic"}
    assert rep["gates"]["with_grad"] == 1


#: the model switches that make the project's form differ from the paper's
SWITCHES = ("skin_prior", "lbs_start", "gate_init", "collision_projection", "blend_shape",
            "strain_limit", "accel_unit", "input_norm", "local_frame")


def test_the_paper_form_is_the_model_and_its_config():
    """The model's defaults are the project's form; the paper's form (PAPER_FORM,
    GarTrans.paper, recipes/ablations/paper.yaml) flips each switch, and the packaged
    recipe leaves every switch at the model's default (written once)."""
    model = {k: p.default for k, p in inspect.signature(GarTrans.__init__).parameters.items()
             if p.default is not inspect.Parameter.empty}
    config = yaml.safe_load(recipe_path("gartrans").read_text())["model"]["init_args"]
    config = config["model"].get("init_args") or {}
    assert not set(SWITCHES) & set(config)
    assert set(PAPER_FORM) == set(SWITCHES)
    assert all(PAPER_FORM[k] != model[k] for k in SWITCHES if k != "gate_init")
    paper = yaml.safe_load(recipe_path("ablations/paper").read_text())["model"]["init_args"]
    paper = paper["model"]["init_args"]
    assert {k: paper.get(k, model[k]) for k in SWITCHES} == PAPER_FORM
    assert GarTrans.paper(3, 10).init_args == dict(GarTrans(3, 10).init_args, **PAPER_FORM)


@pytest.mark.parametrize("layer", ["sat", "gt", "gat"])
def test_attention_stack_initialisation_is_kaiming(layer):
    """§4.1: every linear map of the attention stacks, PyG ``Linear`` included, is
    Kaiming-uniform with ``a = sqrt(5)``: within ``1 / sqrt(fan_in)``, with the uniform
    distribution's standard deviation ``bound / sqrt(3)``."""
    torch.manual_seed(0)
    stack = AttentionStack(layer, 64, [128, 128, 3], 4, 4, "elu", last_act=False)
    with torch.no_grad():
        for m in stack.modules():  # spoil every weight: reset_parameters must redo them
            if isinstance(m, (torch.nn.Linear, PyGLinear)):
                m.weight.fill_(7.0)
    stack.reset_parameters()
    seen = 0
    for m in stack.modules():
        if isinstance(m, (torch.nn.Linear, PyGLinear)) and m.weight.numel() >= 512:
            w = m.weight.detach()
            bound = 1.0 / w.shape[1] ** 0.5
            assert float(w.abs().max()) <= bound + 1e-7
            assert abs(float(w.std()) / (bound / 3 ** 0.5) - 1) < 0.15
            seen += 1
    assert seen >= 3


def _earlier_layout(module, path, flat=True, **changes) -> dict:
    """``module`` saved as a stamped checkpoint of an earlier layout: ``flat``, the model's
    settings among the module's (no model spec); ``changes`` added to the module's
    hyper-parameters (options since removed).  Returns what was saved."""
    hp = dict(module.hparams, **changes)
    if flat:
        hp = {**{k: v for k, v in hp.items() if k != "model"}, **module.model.init_args}
    ckpt = {"state_dict": module.state_dict(), "hyper_parameters": hp,
            "pytorch-lightning_version": L.__version__}
    stamp_checkpoint(ckpt)
    torch.save(ckpt, path)
    return ckpt


@pytest.mark.parametrize("layout", [{"flat": True}, {"flat": False, "garment_state": False},
                                    {"flat": False, "motion_history": 3}])
def test_a_checkpoint_of_an_earlier_layout_is_refused_saying_to_retrain(dm, tmp_path,
                                                                        layout):
    """There is no conversion of earlier layouts: a checkpoint whose hyper-parameters this
    version does not take is refused in one line naming them and saying to retrain."""
    _earlier_layout(gartrans(dm), tmp_path / "old.ckpt", **layout)
    with pytest.raises(CheckpointError) as e:
        GarTransModule.load_from_checkpoint(tmp_path / "old.ckpt")
    msg = str(e.value)
    assert "earlier layout of GarTransModule" in msg and "retrain it" in msg
    assert "\n" not in msg
    named = [k for k in layout if k != "flat"] or ["rest_layer"]
    assert all(k in msg for k in named), msg


def test_an_edited_checkpoint_is_refused_and_an_override_is_no_edit(dm, tmp_path):
    """Lightning writes a keyword override into the loaded hyper-parameters before the
    digest was checked (every override was refused); an edited file still is."""
    module = gartrans(dm)
    ckpt = _earlier_layout(module, tmp_path / "m.ckpt", flat=False)
    assert GarTransModule.load_from_checkpoint(tmp_path / "m.ckpt", lr=1e-4).hparams.lr \
        == 1e-4
    ckpt["hyper_parameters"]["lr"] = 0.5
    torch.save(ckpt, tmp_path / "edited.ckpt")
    for kw in ({}, {"lr": 1e-4}):
        with pytest.raises(CheckpointError, match="integrity digest"):
            GarTransModule.load_from_checkpoint(tmp_path / "edited.ckpt", **kw)


def test_model_can_be_built_under_no_grad(dm):
    """Building GarTrans inside ``torch.no_grad()`` crashed ("element 0 of tensors does not
    require grad"): the attention stacks find their dead edge outputs by a backward pass."""
    with torch.no_grad():
        module = gartrans(dm)
    assert any(p.requires_grad for p in module.model.dynamic.parameters())


def test_input_normalisers_feed_the_stacks_standardised_features(dm, tmp_path):
    """``input_norm``: in training, the first call's statistics are that call's rows, so
    each stack gets exactly ``(x - mean) / std`` of its raw features (computed here with
    torch's own mean and population std); in eval the statistics stay; they travel in
    the checkpoint; without ``input_norm`` the model has no such buffers."""
    module = gartrans(dm, input_norm=True).train()
    model, item = module.model, dm.train_set[1]
    seen = {}

    def keep(name):
        def hook(mod, args, out):
            seen[name] = (args[0].detach().clone(), out.detach().clone())
        return hook

    def keep_stack_input(name):
        def pre(mod, args):
            seen[name] = (args[0].detach().clone(), args[2].detach().clone())
        return pre

    for name in ("rest_norm", "rest_edge_norm", "dynamic_norm", "dynamic_edge_norm"):
        getattr(model, name).register_forward_hook(keep(name))
    model.dynamic.register_forward_pre_hook(keep_stack_input("dynamic"))
    model.rest_attn.register_forward_pre_hook(keep_stack_input("rest_attn"))
    module(item)
    for name in ("rest_norm", "rest_edge_norm", "dynamic_norm", "dynamic_edge_norm"):
        raw, out = seen[name]
        rows = raw.double()
        want = (rows - rows.mean(0)) / rows.std(0, unbiased=False).clamp_min(1e-8)
        torch.testing.assert_close(out.double(), want, atol=1e-4, rtol=1e-4)
        assert int(getattr(model, name).updates) == 1
    # what the stacks see is the normalisers' output
    torch.testing.assert_close(seen["dynamic"][0], seen["dynamic_norm"][1])
    torch.testing.assert_close(seen["dynamic"][1], seen["dynamic_edge_norm"][1])
    torch.testing.assert_close(seen["rest_attn"][1], seen["rest_edge_norm"][1])
    module.eval()
    with torch.no_grad():
        first = module(item)["final"]
    assert int(model.dynamic_norm.updates) == 1  # eval does not update
    path = tmp_path / "norm.ckpt"
    ckpt = {"state_dict": module.state_dict(), "hyper_parameters": dict(module.hparams),
            "pytorch-lightning_version": L.__version__}
    stamp_checkpoint(ckpt)
    torch.save(ckpt, path)
    loaded = GarTransModule.load_from_checkpoint(path).eval()
    assert int(loaded.model.dynamic_norm.updates) == 1
    with torch.no_grad():
        torch.testing.assert_close(loaded(item)["final"], first)
    plain = gartrans(dm, input_norm=False)
    assert isinstance(plain.model.dynamic_norm, torch.nn.Identity)
    assert not any("norm" in k for k in plain.state_dict())


@pytest.mark.parametrize("n", [1, 2, 4, 7, 20])
def test_curves_measures_evenly_spaced_sequences(n):
    """``benchmarks/learning.py``'s choice of the measured sequences: ``n`` of them, evenly
    spaced from the first to the last (numpy's rounded ``linspace``), all where ``n`` is
    more than there are."""
    evenly = runpy.run_path(str(Path(__file__).resolve().parents[1] / "benchmarks" /
                                "learning.py"), run_name="evenly_check")["evenly"]
    items = [f"seq{i}" for i in range(7)]
    want = sorted(set(np.rint(np.linspace(0, 6, min(n, 7))).astype(int)))
    assert evenly(items, n) == [items[i] for i in want]
    assert len(evenly(items, n)) == min(n, 7)


def test_curves_table_means_over_seeds_and_tests_pairs_against_scipy(tmp_path):
    """``benchmarks/learning.py``'s curves table: the mean ± std over seeds of each
    variant's last E_dist / LBS, and scipy's paired Wilcoxon test over (seed, sequence)."""
    bench = runpy.run_path(str(Path(__file__).resolve().parents[1] / "benchmarks" /
                               "learning.py"), run_name="curves_table_check")
    g = torch.Generator().manual_seed(0)
    seqs = [f"s{i}" for i in range(5)]
    lbs = {"train": 2.0, "test": 4.0}

    def run(seed, shift):
        errs = {q: float(4.0 + shift + 0.3 * torch.rand((), generator=g)) for q in seqs}
        last = {"step": 10, "train": 1.8 + shift, "test": sum(errs.values()) / len(errs),
                "test_sequences": errs, "train_sequences": {"t0": 1.8, "t1": 1.8}}
        return {"seed": seed, "status": "ok",
                "curve": [{"step": 0, "train": 2.0, "test": 4.0}, last]}

    res = {"lbs": lbs, "steps": 10, "seeds": [0, 1, 2], "sequences": {"test": {
        q: {"group": f"g{i % 2}", "frames": 10 + i, "lbs": 4.0} for i, q in enumerate(seqs)}},
        "variants": {
        "a": {"runs": [run(s, 0.0) for s in range(3)]},
        "b": {"runs": [run(s, -0.2) for s in range(3)]}}}

    lines = bench["curves_markdown"](res)
    row = next(line for line in lines if line.startswith("| b |")).split(" | ")
    tests = [r["curve"][-1]["test"] / 4.0 for r in res["variants"]["b"]["runs"]]
    assert row[3] == f"{statistics.mean(tests):.3f} ± {statistics.stdev(tests):.3f}"
    x = [r["curve"][-1]["test_sequences"][q] for r in res["variants"]["b"]["runs"] for q in seqs]
    y = [r["curve"][-1]["test_sequences"][q] for r in res["variants"]["a"]["runs"] for q in seqs]
    assert row[5].startswith(f"{wilcoxon(x, y).pvalue:.2g} (")
    assert next(line for line in lines if line.startswith("| a |")).split(" | ")[5] == "—"
    assert "over 2 sequences, test 4.000 cm over 5" in lines[0]
    # the same two variants run in two processes, merged: the same table
    for name in ("a", "b"):
        part = dict(res, command=f"run {name}", variants={name: res["variants"][name]})
        (tmp_path / f"{name}.json").write_text(json.dumps(part))
    merged = bench["merge_curves"]([tmp_path / "a.json", tmp_path / "b.json"])
    assert bench["curves_markdown"](merged) == lines
    assert [src["command"] for src in merged["sources"]] == ["run a", "run b"]
    (tmp_path / "c.json").write_text(json.dumps(dict(res, lbs={"train": 2.0, "test": 4.5})))
    with pytest.raises(ValueError, match="another lbs"):
        bench["merge_curves"]([tmp_path / "a.json", tmp_path / "c.json"])
    # each seed of each variant run in its own process, merged in any order: the same table
    for name in ("a", "b"):
        for run in res["variants"][name]["runs"]:
            part = dict(res, command=f"run {name} {run['seed']}", seeds=[run["seed"]],
                        variants={name: {"runs": [run]}})
            (tmp_path / f"{name}-s{run['seed']}.json").write_text(json.dumps(part))
    files = [tmp_path / f"{name}-s{s}.json" for name in ("a", "b") for s in (2, 0, 1)]
    by_seed = bench["merge_curves"](files)
    assert by_seed["seeds"] == [0, 1, 2]
    assert bench["curves_markdown"](by_seed) == lines
    # a variant with fewer seeds than the table says so in its rows
    fewer = bench["merge_curves"](files[:3] + files[4:])
    assert fewer["seeds"] == [0, 1, 2]
    assert sum(line.startswith("| b (seeds 0, 1) |")  # the table and the group table
               for line in bench["curves_markdown"](fewer)) == 2
    other = json.loads((tmp_path / "a-s1.json").read_text())
    other["variants"]["a"]["settings"] = {"model": "another"}
    (tmp_path / "a-other.json").write_text(json.dumps(other))
    with pytest.raises(ValueError, match="more than one file, with other settings"):
        bench["merge_curves"]([tmp_path / "a-s0.json", tmp_path / "a-other.json"])
    # a variant in two files: kept once where a rerun reproduced its errors (timings
    # differ), refused where an error differs
    rerun = json.loads((tmp_path / "a.json").read_text())
    for r in rerun["variants"]["a"]["runs"]:
        r["seconds"] = r.get("seconds", 0.0) + 1.0
        for point in r["curve"]:
            point["train_seconds"] = point.get("train_seconds", 0.0) + 1.0
    (tmp_path / "a2.json").write_text(json.dumps(rerun))
    twice = bench["merge_curves"]([tmp_path / "a.json", tmp_path / "b.json", tmp_path / "a2.json"])
    assert bench["curves_markdown"](twice) == lines
    rerun["variants"]["a"]["runs"][0]["curve"][-1]["test"] += 1e-6
    (tmp_path / "a3.json").write_text(json.dumps(rerun))
    with pytest.raises(ValueError, match="more than one file, with other errors"):
        bench["merge_curves"]([tmp_path / "a.json", tmp_path / "a3.json"])
    # a merged file's variants, some kept: the reference is the first kept
    (tmp_path / "ab.json").write_text(json.dumps(dict(merged, command="merge a b")))
    only_b = bench["merge_curves"]([tmp_path / "ab.json"], only=["b"])
    assert list(only_b["variants"]) == ["b"]
    assert next(line for line in bench["curves_markdown"](only_b)
                if line.startswith("| b |")).split(" | ")[5] == "—"
    with pytest.raises(ValueError, match="in none of the files"):
        bench["merge_curves"]([tmp_path / "a.json"], only=["b"])
    # every run failed: the table still renders, naming the failure
    failed = dict(res, sequences={}, variants={"a": {"runs": [
        {"seed": 0, "status": "RuntimeError: boom", "curve": []}]}})
    assert bench["curves_markdown"](failed)[-1].endswith("| seed 0: RuntimeError: boom |")


@pytest.fixture(scope="module")
def learning():
    """``benchmarks/learning.py``'s functions."""
    return runpy.run_path(str(Path(__file__).resolve().parents[1] / "benchmarks" /
                          "learning.py"), run_name="oracle_check")


def _hood(dm, loss):
    """The HOOD-style recipe's module with a small model of the class's defaults and
    ``loss`` over the recipe's loss settings."""
    recipe = yaml.safe_load(recipe_path("baselines/hood").read_text())["model"]["init_args"]
    defaults = inspect.signature(HOODStyle.__init__).parameters
    model = {k: defaults[k].default for k in ("fine_blocks", "coarse_blocks", "normalize")}
    return recipe_module("baselines/hood", dm.root, DATA, **{"model.loss": dict(
        recipe["loss"], **loss), "model.model.hidden": 8}, **{f"model.model.{k}": v
                                                              for k, v in model.items()})


def test_objective_rollout_is_free_fall_under_gravity_and_inertia(dm, learning):
    """With gravity and inertia alone the objective's minimiser is known: each free vertex
    falls at ``g w_gravity / w_inertia`` from the LBS garment's first velocity, the pinned
    ones follow the LBS garment."""
    module = _hood(dm, {"enabled": ["gravity", "inertia"],
                        "weights": {"gravity": 0.1, "inertia": 2.0}})
    item = dm.train_set[1]
    lbs = item.skinned().double()
    out = learning["objective_rollout"](module, item).double()
    c = 0.05 * torch.tensor(GRAVITY, dtype=torch.float64) * module.dt ** 2
    t = torch.arange(item.num_frames, dtype=torch.float64).view(-1, 1, 1)
    fall = lbs[0] + t * (lbs[1] - lbs[0]) + c * (t - 1) * t / 2
    pinned = item.pinned_mask().view(1, -1, 1)
    want = torch.where(pinned, lbs, fall)
    torch.testing.assert_close(out, want, rtol=0, atol=2e-6)
    assert out.shape == lbs.shape and item.num_frames >= 3


def test_objective_rollout_lowers_the_objective_of_each_frame(dm, learning):
    module = _hood(dm, {})
    item = dm.train_set[1]
    out = learning["objective_rollout"](module, item, max_iter=5)
    lbs = item.skinned()
    assert torch.equal(out[:2], lbs[:2])  # the LBS garment of frames 0 and 1
    first = item.select(torch.arange(3))  # frame 2, from the same frames 0 and 1
    own = learning["own_objective"]
    best = own(module, first, out[:3])["total"]
    assert best <= own(module, first, torch.stack([lbs[0], lbs[1], 2 * lbs[1] - lbs[0]]))["total"]
    assert best < own(module, first, lbs[:3])["total"]


def test_oracle_refuses_a_method_without_a_physics_objective(tmp_path, learning):
    with pytest.raises(ValueError, match="`variants`.*DA-style"):
        learning["part_oracle"](tmp_path, ["HOOD-style", "DA-style"], 1)


def test_checkpoint_of_other_data_sizes_names_them(dm, tmp_path):
    """A checkpoint scored on data of another body model or Nyström width (as ``train test
    --ckpt_path X`` on another dataset builds the module from that data) is refused
    naming each size, not with torch's "Error(s) in loading state_dict"."""
    ckpt = _earlier_layout(gartrans(dm), tmp_path / "m.ckpt", flat=False)
    init = GarTransModule.saved_hparams(ckpt)["model"]["init_args"]
    other = GarTransModule(GarTrans(**dict(init, num_joints=init["num_joints"] + 2,
                                           nystrom_dim=4)))
    with pytest.raises(CheckpointError, match=r"num_joints \d+ \(the data: \d+\).*nystrom_dim"):
        other.on_load_checkpoint(ckpt)
    ckpt[DATASET_KEY] = {"root": "data/small", "content_sha256": "084747be" + "0" * 56}
    with pytest.raises(CheckpointError, match="dataset 084747be0000 at data/small"):
        other.on_load_checkpoint(ckpt)
    same = GarTransModule(GarTrans(**init))
    same.on_load_checkpoint(ckpt)  # no error: the sizes fit
    same.load_state_dict(ckpt["state_dict"])
    # a garment-agnostic baseline does not depend on the garment's vertex count
    da = BaselineModule(DAStyle(init["num_joints"]))
    da_ckpt = {"state_dict": da.state_dict(), "hyper_parameters": dict(da.hparams)}
    stamp_checkpoint(da_ckpt)
    da.on_load_checkpoint(da_ckpt)
    da_ckpt["hyper_parameters"]["model"]["init_args"]["num_joints"] += 1
    stamp_checkpoint(da_ckpt)
    with pytest.raises(CheckpointError, match="BaselineModule \\(DAStyle\\).*num_joints"):
        da.on_load_checkpoint(da_ckpt)


def test_show_loads_a_baseline_checkpoint_as_its_method(dm, tmp_path):
    """``garmentgnn show --ckpt`` of a DA-style checkpoint: loaded as the baseline it is
    (it was refused as a GarTrans checkpoint with Lightning's "blocked to prevent
    arbitrary code execution") and predicts as ``BaselineModule.predict_garment``."""
    from garmentgnn.training.evaluate import predict  # noqa: PLC0415
    from garmentgnn.training import load_checkpoint  # noqa: PLC0415
    scene = dm.train_set[1]
    L.seed_everything(0)
    da = BaselineModule(DAStyle(scene.num_joints)).eval()
    ckpt = {"state_dict": da.state_dict(), "hyper_parameters": dict(da.hparams),
            "pytorch-lightning_version": L.__version__}
    stamp_checkpoint(ckpt)
    torch.save(ckpt, tmp_path / "da.ckpt")
    loaded = load_checkpoint(tmp_path / "da.ckpt")
    assert isinstance(loaded, BaselineModule) and loaded.method == "da"
    with torch.no_grad():
        torch.testing.assert_close(predict(loaded, scene, "gartrans"), da(scene))


def test_dataset_stamp_is_the_manifests_content_hash(dm):
    """The content hash, and the vertex counts of the training garments as the garments
    of the training split's sequence files have them."""
    man = store.read_manifest(dm.root)
    counts = [store.load_sequence(store.sequence_path(dm.root, r))["positions"].shape[1]
              for r in man["items"] if r["split"] == "train"]
    assert dataset_stamp(dm) == {"root": str(dm.root), "content_sha256": man["content_sha256"],
                                 "num_vertices": [min(counts), max(counts)]}
    assert dataset_stamp(None) == {}


def test_curves_score_valid_frames_and_held_out_groups():
    """``curves`` measures E_dist on an item's valid frames only (the oracle: numpy's mean
    over the kept frames), and its group table is each group's frame-weighted E_dist over
    LBS's on the same sequences, by hand."""
    bench = runpy.run_path(str(Path(__file__).resolve().parents[1] / "benchmarks" /
                               "learning.py"), run_name="groups_check")
    g = torch.Generator().manual_seed(0)
    gt = torch.randn(5, 7, 3, generator=g)
    pred = gt + 0.01 * torch.randn(5, 7, 3, generator=g)
    valid = torch.tensor([True, False, True, True, False])
    item = GarmentInputs(gt=gt, valid=valid)
    per_frame = 100 * np.linalg.norm((pred - gt).numpy(), axis=-1).mean(-1)
    np.testing.assert_allclose(bench["frame_errors"](pred, item).numpy(),
                               per_frame[valid.numpy()], rtol=1e-6)
    assert bench["frame_errors"](pred, GarmentInputs(gt=gt)).shape == (5,)
    facts = {"a": {"group": "unseen body", "frames": 60, "lbs": 4.0},
             "b": {"group": "unseen body", "frames": 20, "lbs": 8.0},
             "c": {"group": "unseen motion", "frames": 50, "lbs": 5.0}}
    last = {"step": 3, "train": 1.0, "test": 2.0,
            "test_sequences": {"a": 2.0, "b": 6.0, "c": 4.0}}
    res = {"lbs": {"train": 2.0, "test": 5.0}, "steps": 3, "seeds": [0],
           "sequences": {"test": facts},
           "variants": {"v": {"runs": [{"seed": 0, "status": "ok", "seconds": 90.0,
                                        "curve": [last]}]}}}
    lines = bench["curves_markdown"](res)
    head = next(i for i, line in enumerate(lines) if line.startswith("Test split by held-out"))
    assert "unseen body 2, unseen motion 1" in lines[head]
    rows = {line.split(" | ")[0]: line.split(" | ") for line in lines[head:] if "|" in line}
    body = (2.0 * 60 + 6.0 * 20) / 80 / ((4.0 * 60 + 8.0 * 20) / 80)
    assert rows["| v"][1:] == [f"{body:.3f}", f"{4.0 / 5.0:.3f} |"]
    assert rows["| LBS (cm)"][1] == f"{(4.0 * 60 + 8.0 * 20) / 80:.3f}"
    assert next(line for line in lines if line.startswith("| v |")).split(" | ")[6] == "1.5"


def test_a_resumed_curves_run_keeps_its_measurements_and_time():
    """What ``curves`` keeps in a run's checkpoint: the measurements so far, the training
    time and the wall time; a resumed run does not measure its start again and counts
    its time on from there."""
    bench = runpy.run_path(str(Path(__file__).resolve().parents[1] / "benchmarks" /
                               "learning.py"), run_name="resume_check")
    first = bench["Probe"]({}, every=1)
    first.rows = [{"step": 0, "train": 1.0}, {"step": 5, "train": 0.9}]
    first.train_seconds, first.seconds_before = 12.5, 100.0
    state = json.loads(json.dumps(first.state_dict()))  # as a checkpoint keeps it
    again = bench["Probe"]({}, every=1)
    again.load_state_dict(state)
    assert again.rows == first.rows and again.train_seconds == 12.5
    assert 100.0 <= again.seconds() < state["seconds"] + 5.0
    measured = []
    again.measure = lambda module, step: measured.append(step)
    again.on_train_start(None, None)
    assert measured == [] and again.train_seconds == 12.5
    fresh = bench["Probe"]({}, every=1)
    fresh.measure = lambda module, step: measured.append(step)
    fresh.on_train_start(None, None)
    assert measured == [0]

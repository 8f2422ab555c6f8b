"""``garmentgnn sweep``: a grid or random search over a recipe's settings on Ray Tune,
each trial trained and scored as one learned run of the bench.

A trial is a recipe: the swept recipe with the trial's values written in (dotted keys
of its configuration, ``model.init_args.lr``; :func:`trial_recipe`), trained on the
dataset's ``train`` split with a bench preset's learned budget and scored on its
``test`` split by :meth:`garmentgnn.bench.learned.LearnedRunner.record` -- the bench's
scores (E_dist and the rest, per held-out group and sequence).  Ray Tune runs the
trials (:class:`ray.tune.Tuner`, one function trainable; ``tune.report`` with the run's
checkpoint folder as a :class:`ray.tune.Checkpoint`); with ``asha``, Ray's Lightning
callback (:class:`~ray.tune.integration.pytorch_lightning.TuneReportCheckpointCallback`)
reports each epoch's training loss with a checkpoint, and
:class:`~ray.tune.schedulers.ASHAScheduler` stops the worst trials early on it.

Written under ``OUT``: ``trials/<NNN>/recipe.yaml`` (the trial's whole recipe: ``garmentgnn
train fit --config OUT/trials/<NNN>/recipe.yaml`` trains it) beside ``score.json`` (its
values, status and scores), ``sweep.md`` (the table, best first) and ``sweep.json``;
``tune/`` is Ray Tune's own folder (results and checkpoints of this machine's trials).
"""
from __future__ import annotations

import difflib
import json
import logging
import math
import os
import shutil
import tempfile
from pathlib import Path
from typing import Any, Dict, List, Optional, Sequence, Tuple

import lightning as L
import yaml

from garmentgnn._files import atomic_write_bytes, atomic_write_json
from garmentgnn._ray import cluster, import_tune
from garmentgnn.bench.curves import quiet_lightning
from garmentgnn.bench.dataset import DatasetInfo
from garmentgnn.bench.methods import LearnedBudget, module_class
from garmentgnn.bench.ray_backend import RayBackend, pack, task_runner
from garmentgnn.bench.records import json_safe
from garmentgnn.bench.timing import num_threads
from garmentgnn.training import load_recipe
from garmentgnn.training.recipes import recipe_path

__all__ = ["DISTRIBUTIONS", "check_space", "parse_space", "sweep", "trial_recipe"]

#: how a swept setting's values are given: ``grid`` and ``choice`` a list of values
#: (every one / one drawn per sample), the others ``LO,HI``
DISTRIBUTIONS = ("grid", "choice", "uniform", "loguniform", "randint")
#: the search's score: the bench's test E_dist (cm); lower is better
METRIC = "E_dist"
#: what ASHA stops trials on: the epoch's training loss the modules log
ASHA_METRIC, ASHA_LOGGED = "train_loss", "train/loss_epoch"
#: a trial's scores kept in ``score.json``
SCORES = ("metrics", "groups", "per_sequence", "test_frames", "epochs", "steps",
          "train_seconds", "timing", "device", "message")


def _value(text: str) -> Any:
    """A value as JSON reads it (``1e-3``, ``true``, ``[1, 2]``), else YAML, else text."""
    try:
        return json.loads(text)
    except ValueError:
        try:
            return yaml.safe_load(text)
        except yaml.YAMLError:
            return text


def parse_space(specs: Dict[str, Sequence[str]]) -> Dict[str, Tuple[str, List[Any]]]:
    """``{distribution: ["KEY=V1,V2", ...]}`` (the command's flags) as ``{key:
    (distribution, values)}``; ``ValueError`` naming the flag for a malformed one, a key
    given twice, and an empty search space."""
    space: Dict[str, Tuple[str, List[Any]]] = {}
    for dist, items in specs.items():
        if dist not in DISTRIBUTIONS:
            raise ValueError(f"`specs`: unknown distribution {dist!r}; choose from "
                             f"{DISTRIBUTIONS}")
        for item in items or ():
            key, eq, values = str(item).partition("=")
            vals = [_value(v.strip()) for v in values.split(",") if v.strip()]
            if not eq or not key.strip() or not vals:
                raise ValueError(f"--{dist} {item!r}: expected KEY=V1,V2,... (e.g. "
                                 "model.init_args.lr=1e-3,3e-3)")
            if dist not in ("grid", "choice") and (
                    len(vals) != 2 or not all(isinstance(v, (int, float)) for v in vals)
                    or not vals[0] < vals[1] or (dist == "loguniform" and vals[0] <= 0)):
                raise ValueError(f"--{dist} {item!r}: expected KEY=LO,HI with numbers "
                                 f"{'0 < ' if dist == 'loguniform' else ''}LO < HI")
            if key.strip() in space:
                raise ValueError(f"--{dist} {key.strip()}: the setting is swept twice; give "
                                 "each key once")
            space[key.strip()] = (dist, vals)
    if not space:
        raise ValueError("the search space is empty: give at least one setting to sweep, "
                         "e.g. --grid model.init_args.lr=1e-3,3e-3")
    return space


def _flat(doc: Any, prefix: str = "") -> List[str]:
    if not isinstance(doc, dict):
        return [prefix[:-1]] if prefix else []
    out = [prefix[:-1]] if prefix else []
    for k, v in doc.items():
        out += _flat(v, f"{prefix}{k}.")
    return out


def check_space(recipe: str, space: Dict[str, Tuple[str, List[Any]]], data) -> None:
    """``ValueError`` naming the first swept key that is no setting of ``recipe`` (its
    configuration as ``garmentgnn train`` parses it on the dataset ``data``), or a
    recipe the bench cannot train."""
    module_class(recipe)  # a ValueError where the recipe trains no method of the bench
    fabric = logging.getLogger("lightning.fabric")  # its "Seed set to 0" line
    level = fabric.level
    fabric.setLevel(logging.ERROR)
    try:
        with quiet_lightning():
            config = load_recipe(recipe, data={"root": str(data), "val_split": None}).config
    finally:
        fabric.setLevel(level)
    keys = set(_flat(config))
    for key, (dist, _) in space.items():
        if key not in keys:
            near = difflib.get_close_matches(key, sorted(keys), n=3)
            raise ValueError(f"--{dist} {key}: the recipe {recipe} has no such setting"
                             + (f" (did you mean {', '.join(near)}?)" if near else "")
                             + f"; `garmentgnn train fit --config {recipe} --print_config` "
                               "lists them")


def trial_recipe(recipe: str, params: Dict[str, Any], data, seed: int,
                 budget: LearnedBudget, text: Optional[str] = None) -> str:
    """``recipe``'s YAML text (or ``text``, its content) with ``params`` (dotted keys)
    written in, and what the bench trains it with: the dataset ``data`` without a
    validation split, the training ``seed``, the ``budget``'s epochs and batch size -- a
    complete recipe of its own."""
    doc = yaml.safe_load(recipe_path(recipe).read_text() if text is None else text) or {}
    bench = {"data.root": str(data), "data.val_split": None,
             "data.batch_size": budget.batch_size, "seed_everything": seed,
             "trainer.max_epochs": budget.epochs}
    for key, value in dict(params, **bench).items():
        node, *path, leaf = [doc, *key.split(".")]
        for part in path:
            if not isinstance(node.get(part), dict):
                node[part] = {}
            node = node[part]
        node[leaf] = value
    return f"# {recipe} with {json.dumps(params, sort_keys=True)}\n" + \
        yaml.safe_dump(doc, sort_keys=False)


class _LastLoss(L.Callback):
    """The last epoch's training loss, for the trial's final report (ASHA wants its
    metric in every report)."""

    value = math.nan

    def on_train_epoch_end(self, trainer: L.Trainer, module: L.LightningModule) -> None:
        self.value = float(trainer.callback_metrics.get(ASHA_LOGGED, math.nan))


def _trial(config: Dict[str, Any], recipe: str, text: str, info: DatasetInfo,
           budget: LearnedBudget, timing: Tuple[Sequence[int], int, int], threads: int,
           seed: int, asha: bool, data_files) -> None:
    """Ray Tune's function trainable: one trial trained and scored as a bench run."""
    from ray import tune  # noqa: PLC0415 (in the trial's worker)
    from ray.tune.integration.pytorch_lightning import (  # noqa: PLC0415
        TuneReportCheckpointCallback)
    with num_threads(threads):
        work = Path(tempfile.mkdtemp(prefix="garmentgnn-trial-"))
        try:
            runner = task_runner(info, budget, timing, data_files, work)
            path = work / "recipe.yaml"
            path.write_text(trial_recipe(recipe, config, runner.data.root, seed, budget,
                                         text))
            last = _LastLoss()
            if asha:
                runner.fit_callbacks = (TuneReportCheckpointCallback(
                    {ASHA_METRIC: ASHA_LOGGED}, on="train_epoch_end"), last)
            rec = runner.record(str(path), seed)
            ok = rec["status"] == "ok"
            score = json_safe({k: rec[k] for k in SCORES if k in rec})
            tune.report({METRIC: rec["metrics"][METRIC] if ok else math.nan,
                         ASHA_METRIC: last.value, "status": rec["status"],
                         "score": json.dumps(score)},
                        checkpoint=tune.Checkpoint.from_directory(str(work / "models")))
        finally:
            shutil.rmtree(work, ignore_errors=True)


def sweep(recipe: str, data: DatasetInfo, out, space: Dict[str, Tuple[str, List[Any]]],
          budget: LearnedBudget, timing: Tuple[Sequence[int], int, int], threads: int,
          samples: int = 1, asha: bool = False, seed: int = 0,
          on: RayBackend = RayBackend()) -> Dict[str, Any]:
    """Run the search (see the module doc) and write ``out``; returns ``sweep.json``'s
    content.  ``space``: :func:`parse_space`; ``timing``: the bench preset's batches,
    warm-up and repeats; ``threads`` CPUs per trial; ``samples``: Ray Tune's
    ``num_samples`` (each grid point that many times, the other distributions drawn
    anew each time); ``asha``: stop trials early on their training loss (at most
    ``budget.epochs`` epochs); ``on``: the cluster, its GPUs per trial and whether the
    dataset is shipped, as for ``bench --backend ray``."""
    os.environ.setdefault("RAY_AIR_NEW_OUTPUT", "0")  # Tune's tables off (verbose=0)
    tune = import_tune()
    from ray.tune.schedulers import ASHAScheduler  # noqa: PLC0415 (optional: ray[tune])
    if not isinstance(samples, int) or samples < 1:
        raise ValueError(f"`samples` (--samples): expected a positive int, got {samples!r}")
    out = Path(out).resolve()
    dists = {"grid": tune.grid_search, "choice": tune.choice, "uniform": tune.uniform,
             "loguniform": tune.loguniform, "randint": tune.randint}
    param_space = {k: dists[d](v) if d in ("grid", "choice") else dists[d](*v)
                   for k, (d, v) in space.items()}
    # max_t: a trial's epochs and its final report (of the test scores)
    scheduler = ASHAScheduler(metric=ASHA_METRIC, mode="min", max_t=budget.epochs + 1,
                              grace_period=1) if asha else None
    with cluster(on.workers, on.address, "sweep"):
        ship = bool(on.address) if on.ship_data is None else on.ship_data
        trainable = tune.with_resources(tune.with_parameters(
            _trial, recipe=recipe, text=recipe_path(recipe).read_text(), info=data,
            budget=budget, timing=timing, threads=threads, seed=seed, asha=asha,
            data_files=pack(data.root) if ship else None), {"cpu": threads, "gpu": on.gpus})
        tuner = tune.Tuner(trainable, param_space=param_space, tune_config=tune.TuneConfig(
            num_samples=samples, scheduler=scheduler, reuse_actors=True),
            run_config=tune.RunConfig(name="trials", storage_path=str(out / "tune"),
                                      verbose=0))
        grid = tuner.fit()
    trials = [_trial_row(r, trial_recipe(recipe, {k: r.config[k] for k in space}, data.root,
                                         seed, budget)) for r in grid]
    trials.sort(key=lambda t: (t[METRIC] is None, t[METRIC] or 0.0))
    for i, t in enumerate(trials):
        folder = out / "trials" / f"{i:03d}"
        atomic_write_bytes(folder / "recipe.yaml", t.pop("recipe").encode())
        t["recipe"] = str(folder / "recipe.yaml")
        atomic_write_json(folder / "score.json", t)
    summary = {"recipe": recipe, "dataset": data.to_json(), "metric": METRIC,
               "space": {k: {"distribution": d, "values": v} for k, (d, v) in space.items()},
               "samples": samples, "asha": asha, "seed": seed, "trials": trials}
    atomic_write_json(out / "sweep.json", json_safe(summary))
    atomic_write_bytes(out / "sweep.md", _table(summary).encode())
    return summary


def _trial_row(result, recipe: str) -> Dict[str, Any]:
    """One finished trial's ``score.json`` (with its recipe text under ``recipe``)."""
    m = result.metrics or {}
    row: Dict[str, Any] = {"params": dict(result.config), "trial_id": m.get("trial_id"),
                           "recipe": recipe,
                           "checkpoint": None if result.checkpoint is None
                           else result.checkpoint.path}
    if result.error is not None:
        row.update(status="failed", message=f"{type(result.error).__name__}: "
                   f"{str(result.error).strip().splitlines()[-1][:500]}", **{METRIC: None})
    elif "score" not in m:
        row.update(status="stopped", message=f"stopped by ASHA after "
                   f"{m.get('training_iteration')} epoch(s), training loss "
                   f"{m.get(ASHA_METRIC)}", **{METRIC: None})
    else:
        row.update(json.loads(m["score"]), status=m["status"])
        row[METRIC] = row.get("metrics", {}).get(METRIC)
    return row


def _table(summary: Dict[str, Any]) -> str:
    keys = list(summary["space"])
    lines = [f"# Sweep of {summary['recipe']}", "",
             f"Dataset {summary['dataset']['name']} ({summary['dataset']['root']}); score: "
             f"test {METRIC} (cm), lower is better; "
             f"{'ASHA on the training loss; ' if summary['asha'] else ''}"
             f"{len(summary['trials'])} trials, best first.", "",
             "| trial | " + " | ".join(f"`{k}`" for k in keys) + f" | {METRIC} | status |",
             "|---" * (len(keys) + 3) + "|"]
    for t in summary["trials"]:
        e = "—" if t[METRIC] is None else f"{t[METRIC]:.4f}"
        name = Path(t["recipe"]).parent.name
        values = " | ".join(str(t["params"][k]) for k in keys)
        lines.append(f"| [{name}](trials/{name}/recipe.yaml) | {values} | {e} | {t['status']} |")
    return "\n".join(lines) + "\n"

"""Building a recipe's module on a test dataset through the loader every caller uses
(:func:`garmentgnn.training.load_recipe`), data settings given as the flags
``garmentgnn train`` takes (so sizes linked from the data follow them)."""
from garmentgnn.training import Recipe, load_recipe


def recipe(name, root, data=None, seed=0, compile_search=False, **settings) -> Recipe:
    """``name``'s recipe on the dataset ``root`` with data settings ``data``
    (``{"chunk": 4, ...}``) and module settings ``settings`` (dotted keys under
    ``model.init_args``: ``{"model.init_args.dynamic_layer": "gat"}`` is given as
    ``**{"model.dynamic_layer": "gat"}``), seeded with ``seed``; the face search not
    compiled unless ``compile_search``."""
    set_ = {"model.init_args.compile_search": compile_search}
    for k, v in settings.items():
        if k.startswith("model."):
            path = k.split(".")[1:]
            k = "model.init_args." + ".init_args.".join(path) if path[0] == "model" else \
                "model.init_args." + ".".join(path)
        set_[k] = v
    return load_recipe(name, args=["--seed_everything", str(seed)],
                       data=dict(root=str(root), **(data or {})), set=set_)


def module(name, root, data=None, **kw):
    """:func:`recipe`'s module."""
    return recipe(name, root, data, **kw).module

"""Parts of ``train_scaling.py`` (and ``step_profile.py``): the callback its timed runs
load by class path, the machine's description."""

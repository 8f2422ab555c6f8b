"""Parts of ``train_scaling.py`` that the timed runs load by class path."""

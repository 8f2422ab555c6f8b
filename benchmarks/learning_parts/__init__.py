"""The parts of ``benchmarks/learning.py`` (its command line): the GarTrans settings and
baseline recipes it compares (:mod:`.variants`), the methods it builds and trains with
the parts that train them (:mod:`.train`: ``grad``, ``overfit``, ``curves``), the curves'
table, merge and plot (:mod:`.curves`) and the physics-objective parts (:mod:`.objective`:
``energy``, ``oracle``)."""

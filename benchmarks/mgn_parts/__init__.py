"""The parts of ``benchmarks/mgn_learn.py`` (its command line): the runs it schedules
(:mod:`.runs`)."""

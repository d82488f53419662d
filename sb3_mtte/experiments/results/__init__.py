"""Results from finished runs: the ``record``, ``plot`` and ``compare`` commands.

- :mod:`~sb3_mtte.experiments.results.runs`: reading run folders and records;
- :mod:`~sb3_mtte.experiments.results.records`: one small JSON record per finished run (``record``);
- :mod:`~sb3_mtte.experiments.results.metrics`: measures of the negative-transfer weighting;
- :mod:`~sb3_mtte.experiments.results.statistics`: intervals, aggregates and tests over runs;
- :mod:`~sb3_mtte.experiments.results.tables`: Table 1 and the tables of results;
- :mod:`~sb3_mtte.experiments.results.bellman_table`: the soft Bellman error table;
- :mod:`~sb3_mtte.experiments.results.figures`, :mod:`~sb3_mtte.experiments.results.summary_figures`: the figures;
- :mod:`~sb3_mtte.experiments.results.figure_layout`: what the figures share (options, styles, panels and labels);
- :mod:`~sb3_mtte.experiments.results.compare`: the pre-registered comparison (``compare``);
- :mod:`~sb3_mtte.experiments.results.runaways`: the runs whose soft Bellman error ran away (for ``compare``);
- :mod:`~sb3_mtte.experiments.results.plot`: every figure and table of a folder (``plot``).

None of them imports rl-zoo3.
"""

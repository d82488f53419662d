"""Experiment tooling of the ``sb3-mtte`` command: a base and three rooms, one journey each.

The base, which imports no room:

- :mod:`~sb3_mtte.experiments.registry` and :mod:`~sb3_mtte.experiments.variants`: the algorithm families and
  variants (zoo keys, classes, labels, order, paper numbers);
- :mod:`~sb3_mtte.experiments.env_ids`: benchmark env ids and the one-task-per-sub-env VecEnv;
- :mod:`~sb3_mtte.experiments.run_info`: ``run_info.json``;
- :mod:`~sb3_mtte.experiments.cli`: the ``sb3-mtte`` dispatcher and the helpers every command shares;
- :mod:`~sb3_mtte.experiments.extras`: the optional install each command needs.

The rooms, each importing the base (and ``playback`` the zoo room too):

- :mod:`~sb3_mtte.experiments.zoo`: training through rl-zoo3 (``train``, ``sweep``);
- :mod:`~sb3_mtte.experiments.results`: records, statistics, figures and tables (``record``, ``plot``,
  ``compare``);
- :mod:`~sb3_mtte.experiments.playback`: a trained model at work (``enjoy``, ``record_video``, ``evaluate``).
"""

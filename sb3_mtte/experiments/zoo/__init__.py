"""Training through rl-zoo3: the ``train`` and ``sweep`` commands.

- :mod:`~sb3_mtte.experiments.zoo.launcher`: ``train`` (rl-zoo's, with resume);
- :mod:`~sb3_mtte.experiments.zoo.manager`: rl-zoo3's ``ExperimentManager`` for multi-task runs;
- :mod:`~sb3_mtte.experiments.zoo.parsers`: rl-zoo's parsers of ``train`` and ``enjoy`` as the package shows them;
- :mod:`~sb3_mtte.experiments.zoo.env_backend`: a run's env keywords checked, its backend (EnvPool) set up;
- :mod:`~sb3_mtte.experiments.zoo.configs`: a zoo key's hyperparameters (family file + variant overrides);
- :mod:`~sb3_mtte.experiments.zoo.training_callbacks`: checkpoints, evaluation and the optuna trial score;
- :mod:`~sb3_mtte.experiments.zoo.run_checkpoints`: the resumable checkpoints of a run folder;
- :mod:`~sb3_mtte.experiments.zoo.run_settings`: the settings a run folder records, which ``--resume`` restores;
- :mod:`~sb3_mtte.experiments.zoo.resume`: what ``--resume`` and ``--exp-id`` do with a folder that holds a run;
- :mod:`~sb3_mtte.experiments.zoo.stopping`: Ctrl-C during training, which stops at a checkpoint;
- :mod:`~sb3_mtte.experiments.zoo.run_logs`: the logs of a run folder;
- :mod:`~sb3_mtte.experiments.zoo.sweep`: a grid of runs on Ray Tune;
- :mod:`~sb3_mtte.experiments.zoo.sweep_trial`, :mod:`~sb3_mtte.experiments.zoo.sweep_run`: one trial's worker
  (tuned, pinned) and its run;
- :mod:`~sb3_mtte.experiments.zoo.adapter`: every reach into rl-zoo3 past its public API.

``run_checkpoints`` imports no rl-zoo3: ``evaluate`` loads its models through it.
"""

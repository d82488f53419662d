"""A trained model at work: the ``enjoy``, ``record_video`` and ``evaluate`` commands.

- :mod:`~sb3_mtte.experiments.playback.zoo_playback`: ``enjoy`` (rl-zoo's) and ``record_video``;
- :mod:`~sb3_mtte.experiments.playback.video`: the videos, task by task;
- :mod:`~sb3_mtte.experiments.playback.episode_reporter`: the episode report of ``enjoy``;
- :mod:`~sb3_mtte.experiments.playback.evaluate_model`: per-task success of a saved model (``evaluate``).

``evaluate_model`` imports no rl-zoo3.
"""

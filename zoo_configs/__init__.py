"""The zoo's hyperparameter files (one rl-zoo3 YAML file per algorithm family), shipped as sb3_mtte.zoo_configs."""

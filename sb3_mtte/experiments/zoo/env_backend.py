"""The env keywords of a zoo run checked, and its backend set up, before any run folder is made.

A run trains on Meta-World's own envs (the default) or on EnvPool's (``--env-kwargs backend:"'envpool'"``); its
evaluation always runs on Meta-World's own envs.
"""

from __future__ import annotations

from typing import Any

from sb3_mtte.envs import backend_of, check_env_kwargs, envpool_envs, envpool_vec_env_cls
from sb3_mtte.experiments.env_ids import MultiTaskVecEnvFactory


def check_env_kwargs_flags(
    benchmark: str, env_kwargs: dict[str, Any], eval_env_kwargs: dict[str, Any], eval_env_kwargs_given: Any
) -> None:
    """Refuse an env keyword the benchmark lacks (the nearest valid one named), a ``reward_function_version``
    Meta-World lacks (or one given to a toy), or a backend given to the evaluation, in one line.

    :param eval_env_kwargs_given: ``--eval-env-kwargs`` as given (None when not given).
    """
    for flag, kwargs in (("--env-kwargs", env_kwargs), ("--eval-env-kwargs", eval_env_kwargs)):
        try:
            check_env_kwargs(benchmark, kwargs)
        except (TypeError, ValueError) as error:
            raise SystemExit(f"{flag}: {error}") from None
    if backend_of(eval_env_kwargs_given) != "metaworld":
        raise SystemExit("--eval-env-kwargs: the evaluation runs on Meta-World's own envs: leave backend out of it.")


def prepare_backend(env_kwargs: dict[str, Any], vec_env_factory: MultiTaskVecEnvFactory) -> None:
    """``backend:'envpool'``: refuse a missing EnvPool in one line, and let ``vec_env_factory`` step the pools in
    parallel (each pool's step is sent before any is received). Meta-World's backend changes nothing."""
    if backend_of(env_kwargs) != "envpool":
        return
    try:
        envpool_envs.require_envpool()
    except ImportError as error:
        raise SystemExit(f"--env-kwargs: {error}") from None
    vec_env_factory.vec_env_cls = envpool_vec_env_cls(vec_env_factory.vec_env_cls)


__all__ = ["check_env_kwargs_flags", "prepare_backend"]

"""Tanh-squashed diagonal Gaussian with explicit reparameterisation noise (same maths as SB3's SAC actor).

Every Gaussian head of the package (the actors' pi(a|.) and the encoder's E_phi(z|s, one-hot)) reads a network's
``(..., 2D)`` output through :func:`split_mean_log_std`; every action distribution is :func:`squashed_gaussian`.
"""

from __future__ import annotations

import math

import torch as th

LOG_STD_MIN, LOG_STD_MAX = -20.0, 2.0
_TANH_EPS = 1e-6  # the epsilon SB3's TanhBijector uses in log(1 - tanh(x)^2 + eps)


def split_mean_log_std(params: th.Tensor) -> tuple[th.Tensor, th.Tensor]:
    """Split a ``(..., 2D)`` network output into mean and clamped log-std."""
    mean, log_std = params.chunk(2, dim=-1)
    return mean, log_std.clamp(LOG_STD_MIN, LOG_STD_MAX)


def gaussian_sample(mean: th.Tensor, log_std: th.Tensor, noise: th.Tensor) -> th.Tensor:
    """Reparameterised sample ``mean + std * noise`` of a diagonal Gaussian, ``noise`` standard normal."""
    return mean + log_std.exp() * noise


def squashed_gaussian_sample(
    mean: th.Tensor, log_std: th.Tensor, noise: th.Tensor | None = None
) -> tuple[th.Tensor, th.Tensor]:
    """Reparameterised sample ``a = tanh(mean + std * noise)`` and its log-probability.

    Passing the same ``noise`` twice gives common random numbers (used to compare two policies fairly).

    :param mean: ``(..., A)`` mean of the Gaussian before the tanh.
    :param log_std: ``(..., A)`` its log-std.
    :param noise: ``(..., A)`` standard normal noise, or None to draw it.
    :return: actions ``(..., A)`` and log-probabilities ``(...,)``.
    """
    if noise is None:
        noise = th.randn_like(mean)
    action = th.tanh(gaussian_sample(mean, log_std, noise))
    gaussian_log_prob = -0.5 * noise.pow(2) - log_std - 0.5 * math.log(2 * math.pi)
    log_prob = (gaussian_log_prob - th.log(1.0 - action.pow(2) + _TANH_EPS)).sum(dim=-1)
    return action, log_prob


def squashed_gaussian(params: th.Tensor, noise: th.Tensor | None = None) -> tuple[th.Tensor, th.Tensor]:
    """The actor head: a ``(..., 2A)`` network output to reparameterised actions and their log-probabilities.

    :param params: ``(..., 2A)`` mean and (unclamped) log-std.
    :param noise: ``(..., A)`` standard normal noise, or None to draw it.
    :return: actions ``(..., A)`` and log-probabilities ``(...,)``.
    """
    return squashed_gaussian_sample(*split_mean_log_std(params), noise)


def squashed_gaussian_action(params: th.Tensor, deterministic: bool = False) -> th.Tensor:
    """Actions of the actor head for acting: ``tanh(mean)`` when deterministic, else a sample.

    :param params: ``(..., 2A)`` mean and (unclamped) log-std.
    :param deterministic: return the mode instead of a sample.
    :return: ``(..., A)``.
    """
    if deterministic:
        return th.tanh(params.chunk(2, dim=-1)[0])
    return squashed_gaussian(params)[0]

"""The update hooks: how several combine, when an update calls them, and which ones each algorithm holds."""

from __future__ import annotations

import pytest
import torch as th

from sb3_mtte import MTSAC, MTSACTE, make_mt_env
from sb3_mtte.common.update_hooks import (
    CollapseReset,
    GradientSurgery,
    NegativeTransferWeights,
    UpdateHook,
    UpdateHooks,
)

SMALL = {"learning_starts": 64, "batch_size": 8, "seed": 0, "policy_kwargs": {"net_arch": [16, 16]}}


class Fixed(UpdateHook):
    """Returns fixed masks and weights; combines gradients by taking task 0's."""

    def __init__(self, mask=None, weights=None, combines=False) -> None:
        self.mask, self.weights = mask, weights
        self.combines_gradients = combines

    def loss_mask(self, task_losses):
        return th.ones_like(task_losses) if self.mask is None else th.tensor(self.mask)

    def task_weights(self):
        return None if self.weights is None else th.tensor(self.weights)

    def combine_gradients(self, task_gradients, task_weights):
        return task_gradients[0]


def test_hooks_combine_masks_multiply_the_last_weights_win_one_combines_gradients():
    losses = th.ones(3)
    hooks = UpdateHooks([Fixed(mask=[1.0, 0.0, 1.0]), Fixed(weights=[0.2, 0.3, 0.5]), Fixed(mask=[0.0, 1.0, 1.0])])
    assert hooks.loss_mask(losses).tolist() == [0.0, 0.0, 1.0]
    assert hooks.task_weights().tolist() == pytest.approx([0.2, 0.3, 0.5])
    hooks = UpdateHooks([Fixed(weights=[1.0, 0.0, 0.0]), Fixed(weights=[0.0, 1.0, 0.0]), Fixed()])
    assert hooks.task_weights().tolist() == [0.0, 1.0, 0.0]
    assert UpdateHooks([Fixed()]).task_weights() is None
    grads = th.arange(6.0).reshape(3, 2)
    assert UpdateHooks([Fixed(), Fixed(combines=True)]).combine_gradients(grads, th.ones(3)).tolist() == [0.0, 1.0]
    assert UpdateHooks([Fixed()]).combine_gradients(grads, th.ones(3)).tolist() == [6.0, 9.0]
    with pytest.raises(ValueError, match="At most one update hook"):
        UpdateHooks([GradientSurgery("pcgrad"), Fixed(combines=True)])


class OrderRecorder(UpdateHook):
    """Records the order of the calls and the actor's parameters at each."""

    def attach(self, model):
        self.model, self.calls = model, []

    def _record(self, name):
        self.calls.append((name, [p.detach().clone() for p in self.model.actor.parameters()]))

    def loss_mask(self, task_losses):
        self._record("loss_mask")
        return th.ones_like(task_losses)

    def task_weights(self):
        self._record("task_weights")

    def after_update(self):
        self._record("after_update")


class RecordingMTSAC(MTSAC):
    def update_hooks(self):
        return [*super().update_hooks(), OrderRecorder()]


def test_an_update_calls_mask_then_weights_then_after_the_optimizer_steps():
    model = RecordingMTSAC("MlpPolicy", make_mt_env("toy-conflict"), **SMALL)
    model.learn(68)
    recorder = model.update_hook.hooks[-1]
    assert [name for name, _ in recorder.calls] == ["loss_mask", "task_weights", "after_update"] * model._n_updates
    masked, weighted, after = recorder.calls[0::3], recorder.calls[1::3], recorder.calls[2::3]
    for (_, at_mask), (_, at_weights), (_, at_end) in zip(masked, weighted, after, strict=True):
        assert all(th.equal(a, b) for a, b in zip(at_mask, at_weights, strict=True))  # the actor had not stepped yet
        # it stepped before after_update
        assert all(not th.equal(a, b) for a, b in zip(at_weights, at_end, strict=True))


@pytest.mark.parametrize(
    "algorithm, policy, kwargs, hooks",
    [
        (MTSAC, "MlpPolicy", {}, []),
        (MTSAC, "MlpPolicy", {"gradient_surgery": "cagrad"}, [GradientSurgery]),
        (MTSAC, "MlpPolicy", {"gradient_surgery": "pcgrad", "critic_arch": "shared"}, [GradientSurgery]),
        (MTSAC, "PaCoPolicy", {"gradient_surgery": "pcgrad"}, [GradientSurgery, CollapseReset]),
        (MTSACTE, "MlpPolicy", {}, [NegativeTransferWeights]),
    ],
)
def test_every_algorithm_holds_its_hooks_and_trains(algorithm, policy, kwargs, hooks):
    model = algorithm(policy, make_mt_env("toy-conflict"), **SMALL, **kwargs)
    assert [type(hook) for hook in model.update_hook.hooks] == hooks
    model.learn(72)
    assert model._n_updates > 0
    assert model.actor.keep_rows == (bool(kwargs) and policy == "MlpPolicy")  # the one-pass per-task gradients
    shared_critic = kwargs.get("critic_arch") == "shared"  # else per-task or task-conditioned: nothing to combine
    assert getattr(model.critic, "keep_rows", False) == shared_critic

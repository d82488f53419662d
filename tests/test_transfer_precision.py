"""mu, C_s and w that rounding cannot decide: the transfer matrix at Meta-World's Q scale (Eq. 4-8).

Adding a constant c to every critic output leaves T[k, i] = J_i(theta^k) - J_i(theta) unchanged in exact
arithmetic. On a real MT10 batch with the package's default networks, mu, C_s and w must equal a float64
plain-loop reference for c up to 1e4. The float32 computation, kept as a control, fails there.
"""

from __future__ import annotations

import copy
import math

import pytest
import torch as th
from references import kappa_benign_set, loop_embedding, loop_transfer

from sb3_mtte import MTSACTE, make_mt_env
from sb3_mtte.mtsacte.objectives import select_tasks
from sb3_mtte.mtsacte.transfer import RepresentationBatch, TaskObjectives, transfer_matrix

N_TASKS, BATCH_SIZE, UPDATES = 10, 128, 100
SHIFTS = (0.0, 1e2, 1e3, 1e4)


@pytest.fixture(scope="module")
def mt10_model():
    """MTSACTE with its defaults on MT10, after 100 vector steps of updates, where T has entries of both signs."""
    env = make_mt_env("MT10", seed=0)
    model = MTSACTE("MlpPolicy", env, learning_starts=N_TASKS * 100, buffer_size=20_000, seed=0, device="cpu")
    with th.random.fork_rng():
        th.set_num_threads(1)
        model.learn(N_TASKS * (100 + UPDATES))
    env.close()
    th.manual_seed(3)
    data = model.replay_buffer.sample(BATCH_SIZE)
    batch = RepresentationBatch.draw(data.observations, model.policy.z_dim, model.policy.action_dim)
    return model, batch


def shifted_policy(model: MTSACTE, shift: float):
    """A copy of the model's policy whose critics all output Q + shift (the last layer's bias moved)."""
    policy = copy.deepcopy(model.policy)
    with th.no_grad():
        policy.critic.q_net.layers[-1].bias.add_(shift)
    return policy


def reference_selection(policy, batch: RepresentationBatch, ent_coef: th.Tensor, z: list[th.Tensor], step: float):
    """mu, C_s and w by plain loops on a float64 copy of the networks (Eq. 4-8)."""
    policy64 = copy.deepcopy(policy).double()
    batch64 = RepresentationBatch(batch.obs.double(), batch.z_noise.double(), batch.action_noise.double())
    _, matrix = loop_transfer(policy64, batch64, ent_coef.double(), step, [zi.double() for zi in z])
    mu = [sum(1 for i in range(N_TASKS) if float(matrix[k, i]) < 0) for k in range(N_TASKS)]
    benign = kappa_benign_set(mu, N_TASKS // 2)
    numerators = [math.exp(N_TASKS - m) for m in mu]
    weights = [v / sum(numerators) for v in numerators]
    return matrix, mu, [k in benign for k in range(N_TASKS)], weights


def selections(model: MTSACTE, batch: RepresentationBatch, shift: float, dtype: th.dtype | None = None):
    """The package's mu, C_s, w beside the reference's, at critic outputs + shift (``dtype``: the transfer matrix's,
    the algorithm's default when None)."""
    policy = shifted_policy(model, shift)
    with th.no_grad():
        z = [loop_embedding(policy, batch, i)[0] for i in range(N_TASKS)]
        objectives = TaskObjectives(policy, batch, model.entropy_coefficients, chunk_size=1)
        dtype_kwargs = {} if dtype is None else {"dtype": dtype}
        matrix = transfer_matrix(objectives, th.stack(z), model.nt_step_size, **dtype_kwargs)
    selection = select_tasks(matrix, model.n_select, th.float32)
    reference = reference_selection(policy, batch, model.entropy_coefficients, z, model.nt_step_size)
    return selection, reference


@pytest.mark.parametrize("shift", SHIFTS)
def test_mu_benign_set_and_weights_equal_the_float64_loop_at_large_q(mt10_model, shift):
    model, batch = mt10_model
    selection, (matrix, mu, benign, weights) = selections(model, batch, shift)
    off_diagonal = ~th.eye(N_TASKS, dtype=th.bool)
    assert float(matrix[off_diagonal].abs().median()) < 1e-3  # small entries: the case where rounding could decide
    assert 0 < sum(mu) < N_TASKS * N_TASKS  # signs of both kinds
    assert selection.mu.tolist() == mu
    assert selection.selected.tolist() == benign
    th.testing.assert_close(selection.weights.double(), th.tensor(weights, dtype=th.float64), rtol=1e-6, atol=1e-9)
    # rounding stays far below the entries
    assert float((selection.transfer_matrix - matrix).abs().max()) < 1e-3 * float(matrix[off_diagonal].abs().median())


def test_float32_matrix_is_decided_by_rounding_at_large_q(mt10_model):
    """The control: the same computation in float32 (the old one) counts other signs at Q + 1e4."""
    model, batch = mt10_model
    selection, (matrix, mu, _, _) = selections(model, batch, 1e4, th.float32)
    off_diagonal = ~th.eye(N_TASKS, dtype=th.bool)
    signs_differ = (selection.transfer_matrix < 0) != (matrix < 0)
    assert int(signs_differ[off_diagonal].sum()) >= 10
    assert selection.mu.tolist() != mu

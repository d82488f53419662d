"""Digests of MTSACTE's parameters after a short fixed-seed run on ``toy-conflict``: evidence that two versions of
the package compute the same numbers bit for bit.

Each case trains a small MTSACTE (every recomputation of mu and every J^rep step included) and hashes every tensor
of the policy's state dict, log beta and the last transfer matrix, mu and w (SHA-256 of dtype, shape and bytes).
``--write FILE`` stores the digests (run it on the reference version), otherwise they are compared with FILE:

    PYTHONPATH=/path/to/reference python benchmarks/same_numbers.py --write tests/data/same_numbers.json
    PYTHONPATH=. python benchmarks/same_numbers.py
"""

from __future__ import annotations

import sb3_mtte  # noqa: F401  (first: the package sets OpenMP's spin-wait before torch loads)

# isort: split

import argparse
import hashlib
import json
import sys
from pathlib import Path
from typing import Any

import numpy as np
import torch as th

from sb3_mtte import MTSACTE, make_mt_env

DEFAULT_FILE = Path(__file__).resolve().parents[1] / "tests" / "data" / "same_numbers.json"
ENV_STEPS = 400
CASES: dict[str, dict[str, Any]] = {
    "virtual_step": {},
    "virtual_step_one_pass": {"nt_chunk_size": None},
    "gradient_dot": {"nt_estimator": "gradient_dot"},
}


def digest(value: th.Tensor | np.ndarray) -> str:
    array = value.detach().cpu().numpy() if isinstance(value, th.Tensor) else np.asarray(value)
    header = f"{array.dtype}{array.shape}".encode()
    return hashlib.sha256(header + np.ascontiguousarray(array).tobytes()).hexdigest()


def train_digests(case: str) -> dict[str, str]:
    """Train the case's model for :data:`ENV_STEPS` env steps and return the digest of every tensor by name."""
    env = make_mt_env("toy-conflict", seed=0)
    model = MTSACTE(
        "MlpPolicy",
        env,
        learning_starts=40,
        batch_size=8,
        buffer_size=4_000,
        top_k=3,
        iteration_length=10,
        rep_gradient_steps=2,
        policy_kwargs={"net_arch": [16, 16], "z_dim": 3},
        seed=0,
        device="cpu",
        **CASES[case],
    )
    model.learn(ENV_STEPS)
    env.close()
    tensors = {f"policy.{name}": value for name, value in model.policy.state_dict().items()}
    tensors["log_ent_coef"] = model.log_ent_coef
    for name in ("transfer_matrix", "mu", "task_weights"):
        tensors[name] = getattr(model, name)
    return {name: digest(value) for name, value in tensors.items()}


def all_digests() -> dict[str, dict[str, str]]:
    return {case: train_digests(case) for case in CASES}


def differences(expected: dict[str, dict[str, str]], got: dict[str, dict[str, str]]) -> list[str]:
    """``case/name`` of every digest that differs or is missing on either side."""
    names = {(case, name) for digests in (expected, got) for case in digests for name in digests[case]}
    return sorted(
        f"{case}/{name}" for case, name in names if expected.get(case, {}).get(name) != got.get(case, {}).get(name)
    )


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--write", action="store_true", help="store the digests in FILE instead of comparing")
    parser.add_argument("--file", type=Path, default=DEFAULT_FILE, help="digest file (default: %(default)s)")
    args = parser.parse_args(argv)
    got = all_digests()
    if args.write:
        args.file.write_text(json.dumps(got, indent=1, sort_keys=True) + "\n")
        print(f"wrote {sum(map(len, got.values()))} digests to {args.file}")
        return
    if not args.file.exists():
        sys.exit(f"No digest file {args.file}: write it from the reference version with --write.")
    different = differences(json.loads(args.file.read_text()), got)
    if different:
        sys.exit(f"{len(different)} tensors differ from {args.file}: {', '.join(different)}")
    print(f"identical: {sum(map(len, got.values()))} tensors of {len(got)} cases, bit for bit")


if __name__ == "__main__":
    main()

"""A short fixed-seed MTSACTE run gives, bit for bit, the parameters stored from the reference version
(``benchmarks/same_numbers.py --write``): refactorings of the networks and the transfer code change no number."""

from __future__ import annotations

import json
import sys
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))
from same_numbers import CASES, DEFAULT_FILE, differences, main, train_digests


@pytest.mark.parametrize("case", list(CASES))
def test_parameters_equal_the_reference_bit_for_bit(case):
    expected = json.loads(DEFAULT_FILE.read_text())[case]
    assert differences({case: expected}, {case: train_digests(case)}) == []


def test_differences_name_changed_and_missing_tensors():
    expected = {"a": {"x": "1", "y": "2"}}
    assert differences(expected, {"a": {"x": "1", "y": "2"}}) == []
    assert differences(expected, {"a": {"x": "1", "y": "3", "z": "4"}}) == ["a/y", "a/z"]
    assert differences(expected, {}) == ["a/x", "a/y"]


def test_a_missing_digest_file_exits_with_one_line(tmp_path, monkeypatch):
    monkeypatch.setattr("same_numbers.all_digests", dict)
    with pytest.raises(SystemExit, match="--write"):
        main(["--file", str(tmp_path / "none.json")])

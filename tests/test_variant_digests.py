"""Every existing algorithm gives the parameters, bit for bit, that the digests in ``tests/data`` were written with
(:mod:`variant_digests`: a short seeded run on toy-conflict, CPU, one thread)."""

from __future__ import annotations

import json

import pytest
from variant_digests import CASES, DIGESTS, case_digest


@pytest.mark.parametrize("case", list(CASES))
def test_parameters_equal_the_stored_digest(case):
    assert case_digest(case) == json.loads(DIGESTS.read_text())[case]

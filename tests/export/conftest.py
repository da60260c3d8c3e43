"""Export test fixtures."""

from __future__ import annotations

import pytest


@pytest.fixture
def radiate_sample_or_none(request):
    """The real RADIATE sample folder, or None when it is not available (the test then uses simulated frames only)."""
    try:
        return request.getfixturevalue("radiate_sample")
    except pytest.skip.Exception:
        return None

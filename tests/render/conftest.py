"""Fixtures for rasteriser tests."""

import pytest

from metegs.testing import camera


@pytest.fixture
def cam():
    return camera()

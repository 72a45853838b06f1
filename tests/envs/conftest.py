"""Small fields so the environment tests stay fast."""

import pytest
from env_configs import small_config


@pytest.fixture
def config():
    return small_config()

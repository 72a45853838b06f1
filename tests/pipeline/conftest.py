import pytest

from tests.pipeline.toyscene import ToyScene


@pytest.fixture(scope="session")
def moving_bag(tmp_path_factory):
    """5 s at 1 m/s, already moving at the first sweep, slight turn and pitching body, and
    3 cm ruts that only the back lidar sees."""
    path = tmp_path_factory.mktemp("bags") / "moving"
    scene = ToyScene(columns=256, yaw_rate=0.05, pitch_amp=0.01, noise=0.005, rut_depth=0.03)
    scene.write(path, 5.0)
    return path, scene

import numpy as np
import pytest

from evdnerf_ros.events import make_events


def random_events(rng, n, width=64, height=48, t0=0, span=1_000_000_000):
    t = np.sort(rng.integers(t0, t0 + span, n))
    return make_events(t, rng.integers(0, width, n), rng.integers(0, height, n),
                       rng.choice(np.array([-1, 1], np.int8), n))


@pytest.fixture
def rng():
    return np.random.default_rng(12345)

import os

os.environ.setdefault("WANDB_MODE", "offline")
os.environ.setdefault("WANDB_SILENT", "true")
# No GL backend is forced: nothing but the `rendering` tests may need one (they skip, saying why,
# where no backend works).

import pytest
import torch

# two threads, or one in each of pytest-xdist's workers (``-n 2``: two workers share the two cores)
SUITE_THREADS = 1 if os.environ.get("PYTEST_XDIST_WORKER") else 2
torch.set_num_threads(SUITE_THREADS)


@pytest.fixture(autouse=True)
def _seed():
    torch.manual_seed(0)
    yield
    # a softae command run in-process sets its own thread count (--threads): the next test gets the
    # suite's back (oneDNN's kernels depend on it: at one thread a single row rounds differently on
    # pre-packed and on plain weights, which test_packed_conv_weights_match allows only there)
    torch.set_num_threads(SUITE_THREADS)


def render_or_skip(env):
    """``env.render()``, or skip with the reason when this machine has no offscreen GL backend."""
    from torchrl_softae.envs.robots.rendering import RenderingUnavailable

    try:
        return env.render()
    except RenderingUnavailable as e:
        pytest.skip(str(e))

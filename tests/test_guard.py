
import pytest
import torch
from tensordict import TensorDict
from torchrl.collectors import Collector
from torchrl.data import Bounded, Composite, Unbounded
from torchrl.envs import EnvBase
from torchrl.envs.utils import RandomPolicy, check_env_specs

from torchrl_softae.envs.guard import EnvFaultWarning, GuardedEnv


class FlakyEnv(EnvBase):
    """A 1-D integrator that raises (or returns NaN) at a chosen step of every episode."""

    def __init__(self, fail_at=5, mode="raise"):
        super().__init__()
        self.fail_at, self.mode, self.t = fail_at, mode, 0
        self.observation_spec = Composite(observation=Unbounded((2,)))
        self.action_spec = Bounded(-1.0, 1.0, (1,))
        self.reward_spec = Unbounded((1,))

    def _reset(self, td=None, **kw):
        self.t = 0
        return TensorDict({"observation": torch.zeros(2)}, [])

    def _step(self, td):
        self.t += 1
        obs = td["observation"] + td["action"]
        if self.t == self.fail_at:
            if self.mode == "raise":
                raise RuntimeError("valve array timed out")
            obs = obs * float("nan")
        return TensorDict({"observation": obs, "reward": torch.zeros(1), "done": torch.zeros(1, dtype=torch.bool),
                           "terminated": torch.zeros(1, dtype=torch.bool)}, [])

    def _set_seed(self, seed):
        pass


def test_guarded_env_specs():
    check_env_specs(GuardedEnv(FlakyEnv(fail_at=100)))


@pytest.mark.parametrize("mode, match", [("raise", "valve array timed out"), ("nan", "non-finite 'observation'")])
def test_fault_ends_episode_keeps_data_and_collection_goes_on(mode, match):
    env = GuardedEnv(FlakyEnv(fail_at=5, mode=mode))
    collector = Collector(env, RandomPolicy(env.action_spec), frames_per_batch=12, total_frames=12,
                          auto_register_policy_transforms=False)
    with pytest.warns(EnvFaultWarning, match=match):
        data = next(iter(collector))
    collector.shutdown()
    assert data.shape == (12,)
    fault = data["next", "env_fault"].squeeze(-1)
    assert fault.nonzero().squeeze(-1).tolist() == [4, 9]  # step 5 of each episode
    assert data["next", "terminated"].squeeze(-1)[4] and not data["next", "terminated"].squeeze(-1)[:4].any()
    assert torch.isfinite(data["next", "observation"][:4]).all()  # what came before is intact
    assert env.num_faults == 2

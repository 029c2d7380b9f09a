"""Small analytic TorchRL envs with known optima, for planner tests."""
import torch
from tensordict import TensorDict
from torchrl.data import Bounded, Composite, Unbounded
from torchrl.envs import EnvBase


class PointMassEnv(EnvBase):
    """s' = s + a, reward = -||s' - target||^2; deterministic and batch-unlocked.

    With actions in [-1, 1]^d the optimal H-step plan from s reaches the target with the first
    action when |target - s| <= 1 and stays there with zeros: return 0 exactly.
    """

    deterministic = True

    def __init__(self, dim: int, target: torch.Tensor, nan_region: bool = False):
        super().__init__(batch_size=[])
        self.target = target
        self.nan_region = nan_region
        self.observation_spec = Composite(observation=Unbounded((dim,)))
        self.action_spec = Bounded(-1.0, 1.0, (dim,))
        self.reward_spec = Unbounded((1,))

    @classmethod
    def __new__(cls, *args, **kwargs):
        return super().__new__(cls, *args, _batch_locked=False, **kwargs)

    def _reset(self, td=None, **kw):
        shape = td.shape if td is not None else self.batch_size
        return TensorDict({"observation": torch.zeros(*shape, self.target.shape[-1])}, shape)

    def _step(self, td):
        nxt = td["observation"] + td["action"]
        r = -(nxt - self.target).square().sum(-1, keepdim=True)
        if self.nan_region:  # any action with a[0] > 0.5 "diverges"
            r = torch.where(td["action"][..., :1] > 0.5, torch.full_like(r, float("nan")), r)
        return TensorDict(
            {"observation": nxt, "reward": r, "done": torch.zeros(*td.shape, 1, dtype=torch.bool),
             "terminated": torch.zeros(*td.shape, 1, dtype=torch.bool)},
            td.shape,
        )

    def _set_seed(self, seed):
        pass

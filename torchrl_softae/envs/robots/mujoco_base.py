"""What the MuJoCo robots share: action validation, instability detection, offscreen rendering."""
from __future__ import annotations

import gymnasium as gym
import numpy as np

from torchrl_softae.envs.robots.checks import check_action

__all__ = ["MujocoRobotEnv", "check_action"]


class MujocoRobotEnv(gym.Env):
    """Base of the MuJoCo robots: ``self.model``/``self.data`` are set by the subclass."""

    metadata = {"render_modes": ["rgb_array"]}
    _renderer = None

    def _instability_warnings(self) -> int:
        """MuJoCo's count of NaN/inf/huge qpos, qvel, qacc (it resets the state when it sees one)."""
        w = self._mj.mjtWarning
        return sum(int(self.data.warning[k].number) for k in (w.mjWARN_BADQPOS, w.mjWARN_BADQVEL, w.mjWARN_BADQACC))

    def _simulate(self, substeps: int, before_substep=None) -> bool:
        """Advance ``substeps``; returns ``True`` if MuJoCo reported an instability meanwhile."""
        warn0 = self._instability_warnings()
        for _ in range(substeps):
            if before_substep is not None:
                before_substep()
            self._mj.mj_step(self.model, self.data)
        return self._instability_warnings() > warn0

    def _render_from(self, lookat, distance: float, elevation: float, azimuth: float) -> np.ndarray:
        if self._renderer is None:
            from torchrl_softae.envs.robots.rendering import offscreen_backend

            offscreen_backend()  # GL is loaded here, on the first frame, never at import
            self._renderer = self._mj.Renderer(self.model, 240, 320)
        cam = self._mj.MjvCamera()
        cam.lookat[:] = lookat
        cam.distance, cam.elevation, cam.azimuth = distance, elevation, azimuth
        self._renderer.update_scene(self.data, camera=cam)
        return self._renderer.render().copy()

    def close(self):
        if self._renderer is not None:
            self._renderer.close()
            self._renderer = None

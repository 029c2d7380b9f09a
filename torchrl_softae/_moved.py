"""Import paths that moved when the pipeline left the library (they keep working).

``import torchrl_softae.explore`` still gives the module now at ``torchrl_softae.pipeline.explore``
(the same module object, so patches and ``isinstance`` checks agree). Installing the alias finder
imports nothing: a moved module is loaded only when its old path is imported.
"""
from __future__ import annotations

import importlib
import importlib.abc
import importlib.util
import sys

MOVED = {
    "torchrl_softae.cli": "torchrl_softae.pipeline.cli",
    "torchrl_softae.config": "torchrl_softae.pipeline.config",
    "torchrl_softae.explore": "torchrl_softae.pipeline.explore",
    "torchrl_softae.evaluate": "torchrl_softae.pipeline.evaluate",
    "torchrl_softae.runs": "torchrl_softae.pipeline.runs",
    "torchrl_softae.plotting": "torchrl_softae.pipeline.plots",
    "torchrl_softae.agents": "torchrl_softae.pipeline.builders",
    "torchrl_softae.envs.catalog": "torchrl_softae.pipeline.catalog",
    "torchrl_softae.envs.soft_arm": "torchrl_softae.envs.robots.soft_arm",
    "torchrl_softae.envs.fish": "torchrl_softae.envs.robots.fish",
    "torchrl_softae.envs.msk_leg": "torchrl_softae.envs.robots.msk_leg",
    "torchrl_softae.envs.cosserat": "torchrl_softae.envs.robots.cosserat",
    "torchrl_softae.envs.rotations": "torchrl_softae.envs.robots.rotations",
    "torchrl_softae.envs.checks": "torchrl_softae.envs.robots.checks",
    "torchrl_softae.envs.mujoco_base": "torchrl_softae.envs.robots.mujoco_base",
    "torchrl_softae.envs.sopra": "torchrl_softae.envs.robots.sopra",  # and its submodules
}


def _target(fullname: str) -> str | None:
    for old, new in MOVED.items():
        if fullname == old or fullname.startswith(old + "."):
            return new + fullname[len(old):]
    return None


class _MovedModuleFinder(importlib.abc.MetaPathFinder, importlib.abc.Loader):
    def __init__(self):
        self._real_specs: dict = {}

    def find_spec(self, fullname, path=None, target=None):
        new = _target(fullname)
        if new is None:
            return None
        return importlib.util.spec_from_loader(fullname, self, is_package=True)

    def create_module(self, spec):
        module = importlib.import_module(_target(spec.name))
        self._real_specs[spec.name] = module.__spec__  # importlib overwrites it with the alias spec
        return module

    def exec_module(self, module):
        alias = module.__spec__.name
        module.__spec__ = self._real_specs.pop(alias)


def install() -> None:
    # first in line: a moved package's submodules (``torchrl_softae.envs.sopra.safety``) would
    # otherwise be found on the aliased package's __path__ and loaded a second time
    if not any(isinstance(f, _MovedModuleFinder) for f in sys.meta_path):
        sys.meta_path.insert(0, _MovedModuleFinder())

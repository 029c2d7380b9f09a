"""The house rules: the library never imports the pipeline, no import cycles, one env list, one
method table, old import paths still work, every device, and the examples stand alone."""
import json
import os
import subprocess
import sys
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import pytest
import torch

ROOT = Path(__file__).resolve().parents[1]
LIBRARY = ["torchrl_softae.modules", "torchrl_softae.objectives", "torchrl_softae.envs", "torchrl_softae.envs.robots",
           "torchrl_softae.tasks"]


def _python(code: str, env_extra: dict | None = None, timeout: int = 300) -> str:
    env = {k: v for k, v in os.environ.items() if k not in ("MUJOCO_GL", "PYOPENGL_PLATFORM")}
    env.update(env_extra or {})
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env, timeout=timeout, cwd=ROOT)
    assert out.returncode == 0, out.stderr[-3000:]
    return out.stdout


def test_library_never_imports_the_pipeline():
    code = f"""
import sys, importlib, pkgutil
import torchrl_softae
for name in {LIBRARY!r}:
    pkg = importlib.import_module(name)
    for info in pkgutil.walk_packages(pkg.__path__, name + "."):
        importlib.import_module(info.name)
from torchrl_softae.envs import EnsembleModelEnv, HallucinatedControl, UncertaintyReward, GuardedEnv
from torchrl_softae.modules import EnsembleWorldModel, ICEMPlanner, MPPIPlanner
from torchrl_softae.tasks import tasks_for
tasks_for("SoftArm-v0"); tasks_for("SoPrA-v0")
print(sorted(m for m in sys.modules if m.startswith("torchrl_softae.pipeline")))
"""
    assert _python(code).strip() == "[]"


def test_each_subpackage_imports_alone():
    """A cycle shows up as an ImportError when a module is the first one imported: each module in
    a fresh interpreter, as many at a time as there are cores (an import is single-threaded)."""
    modules = [*LIBRARY, "torchrl_softae.pipeline.cli", "torchrl_softae.pipeline.explore",
               "torchrl_softae.pipeline.evaluate", "torchrl_softae.envs.robots.sopra"]

    def first_import(module):
        try:
            _python(f"import {module}")
        except AssertionError as e:
            return f"{module}: {e}"

    with ThreadPoolExecutor(max_workers=os.cpu_count() or 1) as pool:
        failures = [f for f in pool.map(first_import, modules) if f]
    assert not failures, "\n".join(failures)


def _import_graph(root: Path) -> dict[str, set[str]]:
    """Module -> the package's modules it imports (anywhere in it, also inside functions). A package's
    ``__init__`` only hands names on and is no node: ``from pkg import mod`` is an arrow to ``pkg.mod``."""
    import ast

    modules = {".".join(p.relative_to(root.parent).with_suffix("").parts): p for p in root.rglob("*.py")
               if p.name != "__init__.py"}
    graph = {}
    for name, path in modules.items():
        package = name.rsplit(".", 1)[0]
        targets = set()
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.Import):
                targets |= {a.name for a in node.names}
            elif isinstance(node, ast.ImportFrom):
                base = node.module or ""
                if node.level:
                    parts = package.split(".")
                    base = ".".join(parts[: len(parts) - node.level + 1] + ([base] if base else []))
                targets |= {f"{base}.{a.name}" if f"{base}.{a.name}" in modules else base for a in node.names}
        graph[name] = {t for t in targets if t in modules and t != name}
    return graph


def _cycle(graph: dict[str, set[str]]) -> list[str] | None:
    """One import cycle of ``graph`` (its modules in order), or ``None``."""
    state, stack = {}, []

    def visit(node):
        state[node] = "open"
        stack.append(node)
        for nxt in sorted(graph[node]):
            if state.get(nxt) == "open":
                return stack[stack.index(nxt):] + [nxt]
            if nxt not in state and (found := visit(nxt)):
                return found
        state[node] = "done"
        stack.pop()
        return None

    for node in sorted(graph):
        if node not in state and (found := visit(node)):
            return found
    return None


def test_no_import_cycle_in_the_package():
    graph = _import_graph(Path(__file__).parents[1] / "torchrl_softae")
    assert "torchrl_softae.pipeline.records" in graph["torchrl_softae.pipeline.plots"]  # arrows are read
    assert "torchrl_softae.pipeline.catalog" in graph["torchrl_softae.pipeline.config"]  # inside functions too
    cycle = _cycle(graph)
    assert cycle is None, " -> ".join(cycle)
    # the checker finds a cycle where there is one
    assert _cycle({"a": {"b"}, "b": {"c"}, "c": {"a"}}) == ["a", "b", "c", "a"]


def test_the_model_stands_apart_from_its_engine():
    """The paper's model is one readable file that imports nothing of the package; the engine
    imports the model; every model built through ``torchrl_softae.modules`` has an engine."""
    root = Path(__file__).parents[1] / "torchrl_softae"
    graph = _import_graph(root)
    model = "torchrl_softae.modules.ensemble"
    assert graph[model] == set(), graph[model]
    assert len((root / "modules" / "ensemble.py").read_text().splitlines()) <= 500
    engine = {m for m in graph if m.startswith("torchrl_softae.modules.engine.")}
    assert {"torchrl_softae.modules.engine.network", "torchrl_softae.modules.engine.rollouts"} <= engine
    assert any(model in graph[m] for m in engine)  # the engine imports the model
    from torchrl_softae.modules import EnsembleWorldModel, InferenceEngine

    assert isinstance(EnsembleWorldModel(3, 1, num_cells=8, depth=1).engine, InferenceEngine)


def test_one_env_list_drives_gymnasium_and_the_catalog():
    import gymnasium as gym

    from torchrl_softae.envs.robots import ENVS
    from torchrl_softae.pipeline.catalog import env_ids, get_env_entry

    assert env_ids() == sorted(r.env_id for r in ENVS)
    for r in ENVS:
        if r.entry_point is not None:
            assert gym.registry[r.env_id].entry_point == r.entry_point
            assert gym.registry[r.env_id].max_episode_steps == r.max_episode_steps
    entry = get_env_entry("SoftArm136-v0")
    assert set(entry.tasks) == {"reach-close", "reach-far"} and entry.defaults["episode_length"] == 200
    with pytest.raises(ValueError, match=r"unknown env 'SoftArm-v9': expected a catalog id \(.*SoftArm-v0"):
        get_env_entry("SoftArm-v9")


def test_one_method_table():
    from torchrl_softae.envs.model_env import PROPAGATION_MODES
    from torchrl_softae.pipeline.cli import build_parser
    from torchrl_softae.pipeline.config import ConfigError, make_config
    from torchrl_softae.pipeline.methods import METHODS

    for m in METHODS.values():
        assert m.propagation is None or m.propagation in PROPAGATION_MODES
    help_text = build_parser()._subparsers._group_actions[0].choices["explore"].format_help()
    assert all(name in help_text for name in METHODS)
    with pytest.raises(ConfigError, match="valid methods: random, mean-ae, pets-ae, hucrl, mbpo, mbpo-ts, softae"):
        make_config("Pendulum-v1", "sofae")
    assert METHODS["softae"].run_name(1, 0.5) == "softae-b0.5-s1" and METHODS["random"].run_name(1, 0.5) == "random-s1"


def test_optimistic_evaluation_plans_with_the_runs_beta():
    """Regression: `softae evaluate --propagation optimistic` planned with beta = 2 whatever the run used."""
    from torchrl.data import Bounded

    from torchrl_softae.envs import HallucinatedControl
    from torchrl_softae.modules import EnsembleWorldModel
    from torchrl_softae.pipeline.config import make_config
    from torchrl_softae.pipeline.evaluate import task_policy

    cfg = make_config("Pendulum-v1", "softae", beta=0.5)
    model = EnsembleWorldModel(3, 1, num_cells=8, depth=1)
    task = __import__("torchrl_softae.tasks", fromlist=["tasks_for"]).tasks_for("Pendulum-v1")["swingup"]
    policy = task_policy(cfg, model, task, Bounded(-2.0, 2.0, (1,)), propagation="optimistic")
    transforms = [t for t in policy.planner.env.transform if isinstance(t, HallucinatedControl)]
    assert len(transforms) == 1 and transforms[0].beta == 0.5


DEVICES = ["cpu"] + (["cuda"] if torch.cuda.is_available() else [])


@pytest.mark.parametrize("device", DEVICES)
def test_composition_runs_on_every_device(device):
    from tensordict import TensorDict
    from torchrl.envs import Compose, TransformedEnv

    from torchrl_softae.envs import EnsembleModelEnv, HallucinatedControl, UncertaintyReward
    from torchrl_softae.modules import EnsembleWorldModel, ICEMPlanner
    from torchrl_softae.objectives import EnsembleLoss, EnsembleTrainer

    model = EnsembleWorldModel(4, 2, num_cells=16, depth=2, device=device)
    assert all(p.device.type == device for p in model.parameters())
    x, a = torch.randn(200, 4), torch.rand(200, 2) * 2 - 1
    data = TensorDict({"observation": x, "action": a, ("next", "observation"): x + 0.1 * a.sum(-1, keepdim=True)}, [200])
    EnsembleTrainer(EnsembleLoss(model), lr=1e-3, epochs=2).fit(data)  # CPU data, model on `device`
    hallucinate = HallucinatedControl(beta=2.0)
    env = TransformedEnv(EnsembleModelEnv(model, mode="optimistic", device=device), Compose(hallucinate, UncertaintyReward()))
    planner = ICEMPlanner(env, planning_horizon=3, num_candidates=16, top_k=4, optim_steps=2)
    policy = hallucinate.policy_for_real_env(planner)
    action = policy(TensorDict({"observation": torch.randn(3, 4, device=device)}, [3], device=device))["action"]
    assert action.shape == (3, 2) and action.device.type == device and action.abs().max() <= 1


def test_examples_explore_and_control_zero_shot_without_the_pipeline(tmp_path):
    model = tmp_path / "model.pt"
    code = f"""
import runpy, sys
sys.argv = ["softae_exploration.py", "--episodes", "2", "--episode-length", "25", "--num-cells", "16", "--depth", "2",
            "--horizon", "3", "--num-candidates", "16", "--top-k", "4", "--optim-steps", "2", "--epochs", "2",
            "--lr", "1e-3", "--out", {str(model)!r}, "--wandb-dir", {str(tmp_path / 'wandb')!r}]
runpy.run_path("examples/softae_exploration.py", run_name="__main__")
sys.argv = ["zero_shot_mpc.py", "--model", {str(model)!r}, "--episodes", "1", "--horizon", "3",
            "--num-candidates", "16", "--top-k", "4", "--optim-steps", "2"]
runpy.run_path("examples/zero_shot_mpc.py", run_name="__main__")
print("PIPELINE", sorted(m for m in sys.modules if m.startswith("torchrl_softae.pipeline")))
"""
    out = _python(code, {"WANDB_MODE": "offline", "WANDB_SILENT": "true"})
    assert "episode 2/2: 50 transitions" in out and "swingup: mean return" in out, out
    assert "PIPELINE []" in out
    assert model.exists() and (tmp_path / "wandb").exists()


def test_no_gl_library_is_loaded_unless_something_renders(tmp_path):
    """Without MUJOCO_GL / PYOPENGL_PLATFORM, importing every robot and a short exploration load no
    OpenGL: a machine without OSMesa or EGL cannot fail the Quick start."""
    code = f"""
import sys, importlib, pkgutil
import torchrl_softae.envs.robots as robots
for info in pkgutil.walk_packages(robots.__path__, "torchrl_softae.envs.robots."):
    importlib.import_module(info.name)
import gymnasium as gym
for env_id in ("SoftFish-v0", "MSKLeg-v0"):
    gym.make(env_id).reset(seed=0)
from torchrl_softae.pipeline.cli import main
assert main(["explore", "--env", "Pendulum-v1", "--method", "softae", "--preset", "quick", "--episodes", "1",
             "--episode-length", "20", "--set", "planner.horizon=3", "--set", "train.epochs=1", "--quiet",
             "--wandb", "disabled", "--run-dir", {str(tmp_path / 'run')!r}]) == 0
from mujoco.rendering.classic import gl_context
import os
print(json.dumps({{"opengl": "OpenGL" in sys.modules, "mujoco_gl": os.environ.get("MUJOCO_GL"),
                  "context": getattr(gl_context, "GLContext", None).__module__ if getattr(gl_context, "GLContext", None) else None}}))
""".replace("import sys,", "import json, sys,")
    res = json.loads(_python(code).strip().splitlines()[-1])
    assert res["opengl"] is False and res["mujoco_gl"] is None
    assert res["context"] in (None, "mujoco.glfw")  # MuJoCo's import-time default, never switched to EGL/OSMesa

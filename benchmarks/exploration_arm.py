"""Random vs Mean-AE vs PETS-AE vs SoftAE on the soft arm, zero-shot reach tasks (i) and (ii).

    python benchmarks/exploration_arm.py                         # SoftArm-v0, 3 seeds
    python benchmarks/exploration_arm.py --episodes 2 --seeds 0  # smoke run

Each method explores for EPISODES x 200 transitions (``quick`` preset, iCEM H=10 as in Table S7),
then solves reach-close (i) and reach-far (ii) zero-shot. Reported: held-out normalized MSE on
ramp-controller reaching rollouts (2000 transitions), tip x-z coverage, task returns (sum of
g(d) over 200 steps, max 200) and final tip error. The paper's normalized MSE (its own budget and
held-out set): Random 0.2397, SoftAE 0.0526.
"""
from _exploration import parse, run

if __name__ == "__main__":
    args = parse(__doc__, env="SoftArm-v0", episodes=10, eval_episodes=1)
    run(args, tasks=["reach-close", "reach-far"], overrides=["planner.horizon=10", "heldout_size=2000"],
        metric_keys={"final_error_mm": "final error [mm]"})

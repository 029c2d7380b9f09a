"""Random vs Mean-AE vs PETS-AE vs SoftAE at an equal transition budget on a pendulum.

    python benchmarks/exploration_pendulum.py                        # Pendulum-v1, 3 seeds
    python benchmarks/exploration_pendulum.py --env Pendulum-hanging
    python benchmarks/exploration_pendulum.py --episodes 2 --seeds 0 # smoke run

Each method explores task-agnostically for EPISODES x 200 transitions (``quick`` preset: the
paper's method with a 3 x 128 ensemble and a 100-sample iCEM, H=20), then the same model and
planner solve swing-up zero-shot. Reported per method (mean ± std over seeds): held-out normalized
next-state MSE (2000 uniform state-action transitions of the true pendulum), state coverage (share
of a 20 x 20 angle-velocity grid visited) and the zero-shot swing-up return / upright fraction.
Results: benchmarks/results/exploration_ENV.{md,json} and benchmarks/results/plots/.
"""
from _exploration import parse, run

if __name__ == "__main__":
    args = parse(__doc__, env="Pendulum-v1", episodes=8, eval_episodes=3)
    run(args, tasks=["swingup"], overrides=["planner.horizon=20", "heldout_size=2000"],
        metric_keys={"upright_fraction_last_half": "upright fraction"})

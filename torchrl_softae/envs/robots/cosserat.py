"""A clamped Cosserat rod driven by internal bending couples (PyElastica 1.0), shared by the soft
arm and the SoPrA simulated twin."""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = ["RodParameters", "CosseratRodSim"]


@dataclass
class RodParameters:
    """Geometry and material of the rod, and the integration settings."""

    length: float = 1.0  # [m]
    radius: float = 0.05  # [m]
    density: float = 1000.0  # [kg/m^3]
    youngs_modulus: float = 1e6  # [Pa]
    poisson_ratio: float = 0.5
    n_elements: int = 20
    direction: tuple = (0.0, 0.0, 1.0)  # from the clamped base towards the tip
    normal: tuple = (1.0, 0.0, 0.0)
    damping: float = 2.0  # analytical linear damping rate [1/s]
    filter_order: int = 4  # Laplace dissipation filter (0 = off)
    gravity: bool = False
    dt: float = 2e-4  # [s]
    activation_tau: float = 0.0  # first-order lag of the couples behind their commanded value [s]


class CosseratRodSim:
    """The rod, its couples and a PositionVerlet stepper. ``target_couples`` (3, n - 1) are the
    commanded internal couples in the local frame of the element above each interface (d1, d2, d3);
    ``couples`` follow them with ``activation_tau`` and are applied equal and opposite on
    neighbouring elements, so the rod bends with no net external torque."""

    def __init__(self, params: RodParameters):
        import elastica as ea
        from elastica.timestepper.symplectic_steppers import PositionVerlet

        class RodSimulator(ea.BaseSystemCollection, ea.Constraints, ea.Forcing, ea.Damping):
            pass

        p = self.params = params
        sim = RodSimulator()
        rod = ea.CosseratRod.straight_rod(
            p.n_elements, np.zeros(3), np.asarray(p.direction, float), np.asarray(p.normal, float),
            p.length, p.radius, p.density, youngs_modulus=p.youngs_modulus,
            shear_modulus=p.youngs_modulus / (2 * (1 + p.poisson_ratio)),
        )
        sim.append(rod)
        sim.constrain(rod).using(ea.OneEndFixedBC, constrained_position_idx=(0,), constrained_director_idx=(0,))
        sim.dampen(rod).using(ea.AnalyticalLinearDamper, uniform_damping_constant=p.damping, time_step=p.dt)
        if p.filter_order:
            # low-pass filter on velocities: removes the grid-scale shear/twist modes that abrupt
            # couple switching excites (Elastica's recommended remedy); bending is left intact
            sim.dampen(rod).using(ea.LaplaceDissipationFilter, filter_order=p.filter_order)
        owner = self

        class InternalCouples(ea.NoForces):
            # Each interface couple acts on the element above it and, reversed, on the element below,
            # both as bending couples in their own material frames. (Transporting the reaction through
            # the lab frame instead would feed the small frame mismatch into torsion, which nothing
            # actuates or damps much: measured 120 rad/s of spurious twist under bang-bang commands.)
            def apply_torques(self, system, time=0.0):
                local = owner.couples
                system.external_torques[:, 1:] += local
                system.external_torques[:, :-1] -= local

        self.couples = np.zeros((3, p.n_elements - 1))  # applied now
        self.target_couples = np.zeros((3, p.n_elements - 1))  # commanded
        sim.add_forcing_to(rod).using(InternalCouples)
        if p.gravity:
            sim.add_forcing_to(rod).using(ea.GravityForces, acc_gravity=np.array([0.0, 0.0, -9.81]))
        sim.finalize()
        self.sim, self.rod, self._stepper, self.time = sim, rod, PositionVerlet(), 0.0
        keys = ("position_collection", "velocity_collection", "director_collection",
                "omega_collection", "acceleration_collection", "alpha_collection")
        self._initial = {k: getattr(rod, k).copy() for k in keys}

    def restore(self) -> None:
        """Back to the straight rod at rest, no couples."""
        for k, v in self._initial.items():
            getattr(self.rod, k)[...] = v
        self.couples[...] = 0.0
        self.target_couples[...] = 0.0
        self.time = 0.0

    def advance(self, duration: float) -> None:
        """Integrate ``duration`` seconds; the couples track ``target_couples`` with the activation lag
        (actuators build torque over tens of ms: a step command does not hit the rod as an impulse)."""
        p = self.params
        steps = int(round(duration / p.dt))
        alpha = 1.0 - np.exp(-p.dt / p.activation_tau) if p.activation_tau > 0 else 1.0
        with np.errstate(all="ignore"):
            for _ in range(steps):
                self.couples += alpha * (self.target_couples - self.couples)
                self.time = self._stepper.step(self.sim, self.time, p.dt)

    def node_positions(self) -> np.ndarray:
        """(n + 1, 3) relative to the clamped base."""
        pos = self.rod.position_collection
        return (pos - pos[:, :1]).T.copy()

    def max_speed(self) -> float:
        return float(np.abs(self.rod.velocity_collection).max())

    def element_rotations(self, idx) -> np.ndarray:
        """(k, 3, 3) local-to-lab rotation matrices of elements ``idx``."""
        return np.transpose(self.rod.director_collection[:, :, idx], (2, 1, 0)).copy()

    def element_omega_lab(self) -> np.ndarray:
        """(n, 3) element angular velocities in the lab frame."""
        return np.einsum("jin,jn->ni", self.rod.director_collection, self.rod.omega_collection)

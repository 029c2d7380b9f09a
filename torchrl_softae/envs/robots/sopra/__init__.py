"""SoPrA, the pneumatic two-segment soft arm: hardware backends, safety layer, simulated twin, env."""
from torchrl_softae.envs.robots.sopra.backends import (
    ModbusMap,
    ModbusValveArray,
    MotionCapture,
    Pose,
    QualisysMotionCapture,
    RecordingValveArray,
    ValveArray,
)
from torchrl_softae.envs.robots.sopra.env import SOPRA_TARGETS, MonotonicClock, SoPrAEnv, sopra_layout
from torchrl_softae.envs.robots.sopra.safety import SafetyFault, SafetyLayer, SafetyLimits
from torchrl_softae.envs.robots.sopra.sim import SoPrASim, SoPrATwinParameters

__all__ = [
    "SoPrAEnv", "SafetyLayer", "SafetyLimits", "SafetyFault", "SoPrASim", "SoPrATwinParameters",
    "QualisysMotionCapture", "ModbusValveArray", "ModbusMap", "RecordingValveArray", "MotionCapture",
    "ValveArray", "Pose", "MonotonicClock", "sopra_layout", "SOPRA_TARGETS",
]

"""The control layer (imports only ``model``): the controller interface, the baselines, the
three-gain law and the learned gain policy as a controller (it does not import the trainer)."""

from jaxtraffic.control.adaptive import AdaptiveSettings, EstimatorState, adaptive_backstepping
from jaxtraffic.control.base import Controller, Observation, saturate, takes_delay, tell_delay
from jaxtraffic.control.baselines import (
    BacksteppingSettings,
    LyapunovSettings,
    backstepping,
    lyapunov,
    lyapunov_input,
    lyapunov_law,
    open_loop,
    predict,
)
from jaxtraffic.control.filters import measurement_filter
from jaxtraffic.control.gain_law import (
    GAIN_NAMES,
    DelaySchedule,
    constant_gains,
    gain_law,
    lyapunov_equivalent_gains,
    schedule_gains,
    scheduled_gains,
)
from jaxtraffic.control.gain_policy import (
    equilibrium_gains,
    gain_target_controller,
    policy_controller,
)
from jaxtraffic.control.noise import sensor_noise

__all__ = [
    "GAIN_NAMES", "AdaptiveSettings", "EstimatorState", "adaptive_backstepping",
    "BacksteppingSettings", "Controller", "DelaySchedule", "LyapunovSettings", "Observation",
    "backstepping", "constant_gains", "equilibrium_gains", "gain_law", "gain_target_controller", "lyapunov",
    "lyapunov_equivalent_gains", "lyapunov_input", "lyapunov_law", "measurement_filter", "open_loop",
    "policy_controller", "predict",
    "saturate", "sensor_noise", "schedule_gains", "scheduled_gains", "takes_delay", "tell_delay",
]

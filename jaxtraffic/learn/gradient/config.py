"""The gradient trainer's settings (``GradientConfig``) and each policy's defaults (``POLICY_DEFAULTS``).

``learn.gradient.objective`` (the objective, Adam) and ``learn.gradient.cem`` (the cross-entropy method) read it;
``learn.config`` builds it from the command line's flags.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

from jaxtraffic.control.gain_law import FILTER_SIGMA
from jaxtraffic.control.networks import SMALL_HIDDEN

POLICIES = ("gains", "network", "schedule")
METHODS = ("adam", "cem")  # Adam on the gradient of the objective; the cross-entropy method on the map's counts


@dataclass(frozen=True)
class GradientConfig:
    """Gradient-training settings. Shape-setting fields (scenario grid, horizon, policy, network)
    are static; the objective weights and Adam's settings are traced (``Weights``, ``lr``...).

    The training scenarios are the Cartesian product of ``delays`` (s, multiples of dt) x
    ``alphas`` x ``amplitudes`` (veh/m) x ``wavenumbers`` x ``phases`` (rad) of the initial
    cosine perturbation (``sim.initial.paper_initial_condition``).
    """

    policy: str = "gains"
    delays: tuple[float, ...] = (3.0, 4.0, 5.0)
    alphas: tuple[float, ...] = (0.15,)
    amplitudes: tuple[float, ...] = (0.010,)
    wavenumbers: tuple[int, ...] = (4,)
    phases: tuple[float, ...] = (0.0,)
    horizon_s: float = 300.0
    record_every: int = 10
    steps_per_chunk: int = 5
    hidden: tuple[int, ...] = SMALL_HIDDEN
    gain_max: float = 3.0
    gain_filter: float = 0.2
    lr: float = 0.05
    max_grad_norm: float = 1.0
    reward_weight: float = 1.0
    wave_weight: float = 0.0
    comfort_weight: float = 1e-5
    effort_weight: float = 0.0
    init_gains: tuple[float, float, float] = (0.0, 0.0, 0.0)
    steps: int = 40  # Adam steps in all
    scenario_clip: float = 0.0  # > 0: clip each scenario's gradient to this norm (``objective_and_grad``)
    filter_sigma: float = FILTER_SIGMA  # m, the gain law's Gaussian filter (``control.gain_law``); 0: pointwise
    controller_points: int = 0  # the controller's own grid (``control.adapter``); 0: the plant's
    certificate_weight: float = 0.0  # objective += w * ``certificate_penalty`` (1/s)
    knots: tuple[float, ...] = (0.0, 2.0, 4.0, 6.0, 8.0)  # s, the schedule policy's knot delays
    method: str = "adam"  # "cem": ``learn.gradient.cem`` (derivative-free; steps are its generations)
    cem_population: int = 24  # CEM: parameter sets per generation
    cem_sigma: float = 0.3  # CEM: initial standard deviation of the search distribution (dimensionless gains)

    def __post_init__(self) -> None:
        if self.policy not in POLICIES:
            raise ValueError(f"policy must be one of {POLICIES}, got {self.policy!r}")
        for name in ("delays", "alphas", "amplitudes", "wavenumbers", "phases"):
            if len(getattr(self, name)) < 1:
                raise ValueError(f"{name} needs at least one value")
        if min(self.delays) < 0:
            raise ValueError(f"delays must be >= 0 s, got {self.delays}")
        if not all(0.0 < a <= 1.0 for a in self.alphas):
            raise ValueError(f"alphas must lie in (0, 1], got {self.alphas}")
        if self.record_every < 1 or self.steps_per_chunk < 1 or self.steps < 1:
            raise ValueError("record_every, steps_per_chunk and steps must be >= 1")
        for name in ("lr", "max_grad_norm", "gain_max"):
            if not getattr(self, name) > 0:
                raise ValueError(f"{name} must be > 0, got {getattr(self, name)}")
        if not 0.0 < self.gain_filter <= 1.0:
            raise ValueError(f"gain_filter must lie in (0, 1], got {self.gain_filter}")
        for name in ("reward_weight", "wave_weight", "comfort_weight", "effort_weight", "scenario_clip",
                     "certificate_weight"):
            if not getattr(self, name) >= 0:
                raise ValueError(f"{name} must be >= 0, got {getattr(self, name)}")
        if not self.filter_sigma >= 0 or self.controller_points < 0 or self.controller_points in (1, 2):
            raise ValueError(f"filter_sigma must be >= 0 m and controller_points 0 or >= 3, got "
                             f"{self.filter_sigma}, {self.controller_points}")
        if self.method not in METHODS or (self.method == "cem" and self.policy == "network"):
            raise ValueError(f"method must be one of {METHODS} (cem: gains or schedule policy), got {self.method!r} "
                             f"for policy {self.policy!r}")
        if self.cem_population < 2 or not self.cem_sigma > 0:
            raise ValueError(f"cem_population must be >= 2 and cem_sigma > 0, got {self.cem_population}, "
                             f"{self.cem_sigma}")
        if len(self.knots) < 1 or any(b <= a for a, b in zip(self.knots, self.knots[1:], strict=False)):
            raise ValueError(f"knots must be increasing delays, got {self.knots}")
        if self.policy == "network" and max(abs(g) for g in self.init_gains) >= self.gain_max:
            raise ValueError(f"init_gains {self.init_gains} must lie inside (-gain_max, gain_max)")

    @classmethod
    def for_policy(cls, policy: str = "gains", **overrides: Any) -> GradientConfig:
        """The defaults of ``policy`` (``POLICY_DEFAULTS`` over the field defaults), then ``overrides``."""
        if policy not in POLICIES:
            raise ValueError(f"policy must be one of {POLICIES}, got {policy!r}")
        return cls(policy=policy, **{**POLICY_DEFAULTS[policy], **overrides})

    @property
    def n_scenarios(self) -> int:
        return (len(self.delays) * len(self.alphas) * len(self.amplitudes) * len(self.wavenumbers)
                * len(self.phases))


# The network policy: a smaller step (its first layer sees 3 n + 3 inputs), half the steps, and
# plant delays 0-6 s (it is meant to stabilise all of them). The schedule: trained by CEM on the map's own counts
# (learn.gradient.cem; the smooth wave objectives traded divergence badly, BENCHMARKS.md), over the robustness
# map's ranges (delays 0-8 s, alphas 0.05-0.6) on plants offset from both maps' cells (the map is judged on held-out
# plants), 600 s as the map, started from a law that stabilises the nominal plant; the wave objective is its Adam option
POLICY_DEFAULTS: dict[str, dict[str, Any]] = {
    "gains": {},
    "network": {"lr": 3e-3, "steps": 20, "delays": (0.0, 3.0, 6.0)},
    "schedule": {"method": "cem", "steps": 10, "delays": (0.3, 1.7, 3.3, 4.7, 6.3, 7.7),
                 "alphas": (0.125, 0.225, 0.325, 0.425, 0.525, 0.575), "horizon_s": 600.0, "reward_weight": 0.0,
                 "wave_weight": 1.0, "comfort_weight": 0.0, "scenario_clip": 1.0, "init_gains": (0.0, -1.0, -1.5)},
}

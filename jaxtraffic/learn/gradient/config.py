"""The gradient trainer's settings (``GradientConfig``) and each policy's defaults (``POLICY_DEFAULTS``).

``learn.gradient.objective`` (the objective, Adam) and ``learn.gradient.cem`` (the cross-entropy method) read it;
a run's config (``runs.config.TrainConfig.grad``) nests it as it is.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

from jaxtraffic.control.gain_law import FILTER_SIGMA
from jaxtraffic.control.networks import SMALL_HIDDEN
from jaxtraffic.fields import check_fields, fail, hyper

POLICIES = ("gains", "network", "schedule", "residual")
METHODS = ("adam", "cem")  # Adam on the gradient of the objective; the cross-entropy method on the map's counts
CEM_FITNESS = ("counts", "mean_l2")  # the CEM's fitness: the map's counts; the fair comparison's time-averaged L2


@dataclass(frozen=True)
class GradientConfig:
    """Gradient-training settings. Shape-setting fields (scenario grid, horizon, policy, network)
    are static; the objective weights and Adam's settings are traced (``Weights``, ``grad_lr``...).

    A run's config nests it as it is (``runs.config.TrainConfig.grad``; ``gain_filter`` and ``filter_sigma`` are
    set from the environment's section, ``hidden`` and ``max_grad_norm`` from PPO's); each field is checked
    against the range in its metadata (``jaxtraffic.fields.hyper``).

    The training scenarios are the Cartesian product of ``train_delays`` (s, multiples of dt) x
    ``train_alphas`` x ``train_amplitudes`` (veh/km) x ``train_wavenumbers`` x ``train_phases`` (rad) of the
    initial cosine perturbation (``sim.initial.paper_initial_condition``), or with ``train_split`` > 0 that many
    scenarios of the scenario distribution's train split (``compare.scenarios``).
    """

    policy: str = hyper("gains", help="gains: three constant gains; network: the actor network PPO trains; "
                        "schedule: gains scheduled in the delay the controller is told; residual: adaptive "
                        "backstepping plus a filtered gain-law correction scheduled in the told delay and the "
                        "estimated alpha",
                        choices=POLICIES)
    train_delays: tuple[float, ...] = hyper((3.0, 4.0, 5.0), lo=0.0, help="plant delays of the scenarios, s")
    train_alphas: tuple[float, ...] = hyper((0.15,), lo=0.0, lo_open=True, hi=1.0, help="plant alphas of the scenarios")
    train_amplitudes: tuple[float, ...] = hyper((10.0,), help="initial perturbation amplitudes, veh/km")
    train_wavenumbers: tuple[int, ...] = hyper((4,), help="initial perturbation wavenumbers")
    train_phases: tuple[float, ...] = hyper((0.0,), help="initial perturbation phases, rad")
    train_horizon_s: float = hyper(300.0, lo=0.0, lo_open=True, help="rollout length of the objective, s")
    record_every: int = hyper(10, lo=1, help="steps between objective samples")
    steps_per_chunk: int = hyper(5, lo=1, help="Adam steps per compiled chunk (progress/checkpoint interval)")
    hidden: tuple[int, ...] = SMALL_HIDDEN  # the network policy's hidden layers (a run: PPOConfig.hidden)
    grad_gain_max: float = hyper(3.0, lo=0.0, lo_open=True, help="network policy: |eta_i| bound")
    gain_filter: float = hyper(0.2, lo=0.0, lo_open=True, hi=1.0)  # (a run: EnvParams.gain_filter)
    grad_lr: float = hyper(0.05, lo=0.0, lo_open=True, help="Adam step size")
    max_grad_norm: float = 1.0  # Adam's global gradient-norm clip
    reward_weight: float = hyper(1.0, lo=0.0, help="objective weight of -mean reward (dimensionless)")
    waves_weight: float = hyper(0.0, lo=0.0, help="objective weight of the wave amplitude (log variance)")
    comfort_weight: float = hyper(1e-5, lo=0.0, help="objective weight of J_comfort")
    init_gains: tuple[float, float, float] = hyper((0.0, 0.0, 0.0), help="initial gains eta1,eta2,eta3")
    grad_steps: int = hyper(40, lo=1, help="Adam steps (cem: generations)")
    scenario_clip: float = hyper(0.0, lo=0.0, help="> 0: clip each scenario's gradient to this norm; 0: off")
    filter_sigma: float = hyper(FILTER_SIGMA, lo=0.0)  # m, the gain law's Gaussian filter; 0: pointwise
    # > 0: the scenarios are this many of the scenario distribution's train split instead of the grid above (a run:
    # EnvConfig.train_split)
    train_split: int = hyper(0, lo=0)
    # each train-split scenario's relative sensor error ~ U(lo, hi) (a run: EnvConfig.train_sensor_noise)
    train_sensor_noise: tuple[float, float] = hyper((0.0, 0.0), lo=0.0, hi=1.0)
    # the controller's own grid (``control.adapter``; the plant's n_points must refine it by an integer factor)
    controller_points: int = hyper(0, lo=0, help="controller's grid points (0: the plant's)")
    schedule_knots: tuple[float, ...] = hyper((0.0, 2.0, 4.0, 6.0, 8.0), help="schedule policy: its knot delays, s")
    grad_method: str = hyper("adam", help="adam: Adam on the objective; cem: the cross-entropy method on the map's "
                             "counts", choices=METHODS)
    cem_population: int = hyper(24, lo=2, help="cem: parameter sets per generation")
    cem_sigma: float = hyper(0.3, lo=0.0, lo_open=True, help="cem: initial std of the search over the gains")
    cem_tie_weight: float = hyper(0.01, lo=0.0, help="cem: fitness weight of the mean log final std_x(rho) "
                                  "(log veh/km) against the counts; small: a tie-breaker between equal counts")
    cem_fitness: str = hyper("counts", help="cem: counts: the map's counts at the horizon (stabilised, diverged); "
                             "mean_l2: minus the time-averaged density L2 over the horizon (veh/km, capped; the "
                             "fair comparison's measure, which the tuned baselines minimise)", choices=CEM_FITNESS)
    residual_alpha_floor: float = hyper(0.0, lo=0.0, hi=1.0, help="residual policy: its table's rows at alpha_hat "
                                        "knots below this stay zero (the adaptive law) and are not trained")

    def __post_init__(self) -> None:
        if self.policy not in POLICIES:
            raise ValueError(f"policy must be one of {POLICIES}, got {self.policy!r}")
        for name in ("train_delays", "train_alphas", "train_amplitudes", "train_wavenumbers", "train_phases"):
            if len(getattr(self, name)) < 1:
                raise ValueError(f"{name} needs at least one value")
        check_fields(self)  # every field's range
        if self.train_sensor_noise[0] > self.train_sensor_noise[1]:
            raise fail("train_sensor_noise", self.train_sensor_noise, "must be (lo, hi) with lo <= hi")
        if self.controller_points != 0 and self.controller_points < 3:  # 0: the plant's grid
            raise fail("controller_points", self.controller_points, "must be >= 3 (0: the plant's grid)")
        if self.grad_method not in METHODS or (self.grad_method == "cem" and self.policy == "network") or (
                self.grad_method == "adam" and self.policy == "residual"):  # its predictor: no reverse mode
            raise ValueError(f"grad_method must be one of {METHODS} (cem: gains, schedule or residual policy; adam: "
                             f"not the residual), got "
                             f"{self.grad_method!r} for policy {self.policy!r}")
        if len(self.schedule_knots) < 1 or any(b <= a for a, b in zip(self.schedule_knots, self.schedule_knots[1:],
                                                                         strict=False)):
            raise ValueError(f"schedule_knots must be increasing delays, got {self.schedule_knots}")
        if self.policy == "network" and max(abs(g) for g in self.init_gains) >= self.grad_gain_max:
            raise ValueError(f"init_gains {self.init_gains} must lie inside (-grad_gain_max, grad_gain_max)")

    @classmethod
    def for_policy(cls, policy: str = "gains", **overrides: Any) -> GradientConfig:
        """The defaults of ``policy`` (``POLICY_DEFAULTS`` over the field defaults), then ``overrides``."""
        if policy not in POLICIES:
            raise ValueError(f"policy must be one of {POLICIES}, got {policy!r}")
        return cls(policy=policy, **{**POLICY_DEFAULTS[policy], **overrides})

    @property
    def n_scenarios(self) -> int:
        if self.train_split:
            return self.train_split
        return (len(self.train_delays) * len(self.train_alphas) * len(self.train_amplitudes)
                * len(self.train_wavenumbers) * len(self.train_phases))


# The network policy: a smaller step (its first layer sees 3 n + 3 inputs), half the steps, and
# plant delays 0-6 s (it is meant to stabilise all of them). The schedule: trained by CEM on the map's own counts
# (learn.gradient.cem; the smooth wave objectives traded divergence badly, docs/model.md section 17), over the
# robustness map's ranges (delays 0-8 s, alphas 0.05-0.6) on plants offset from both maps' cells (the map is judged
# on held-out plants), 600 s as the map, started from a law that stabilises the nominal plant; the wave objective
# is its Adam option
POLICY_DEFAULTS: dict[str, dict[str, Any]] = {
    "gains": {},
    "network": {"grad_lr": 3e-3, "grad_steps": 20, "train_delays": (0.0, 3.0, 6.0)},
    "schedule": {"grad_method": "cem", "grad_steps": 10, "train_delays": (0.3, 1.7, 3.3, 4.7, 6.3, 7.7),
                 "train_alphas": (0.125, 0.225, 0.325, 0.425, 0.525, 0.575), "train_horizon_s": 600.0,
                 "reward_weight": 0.0, "waves_weight": 1.0, "comfort_weight": 0.0, "scenario_clip": 1.0,
                 "init_gains": (0.0, -1.0, -1.5)},
    # the residual on adaptive backstepping (control.adaptive_residual): the schedule's CEM on the same held-out
    # plants, started at zero (the adaptive law), a coarser delay table (knots 0, 4, 8 s x alpha_hat 0.05, 0.3, 0.6),
    # judged at 300 s: at 600 s the adaptive law already stabilises every consistent training plant and the counts
    # no longer tell laws apart; at 300 s it has stabilised 3 of 36 (docs/model.md section 18.2), so they reward speed.
    # The table's alpha_hat = 0.05 row, below every training plant's alpha, is held at the adaptive law (zero): trained,
    # it was extrapolated and lost the map's (2 s, 0.05) cell for seed 1 (docs/model.md section 18.2)
    "residual": {"grad_method": "cem", "grad_steps": 10, "train_delays": (0.3, 1.7, 3.3, 4.7, 6.3, 7.7),
                 "train_alphas": (0.125, 0.225, 0.325, 0.425, 0.525, 0.575), "train_horizon_s": 300.0,
                 "reward_weight": 0.0, "waves_weight": 1.0, "comfort_weight": 0.0, "scenario_clip": 1.0,
                 "schedule_knots": (0.0, 4.0, 8.0), "cem_population": 12, "residual_alpha_floor": 0.1},
}

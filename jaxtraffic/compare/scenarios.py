"""A distribution of scenarios and its train / test split (docs/model.md section 20).

A scenario is a plant (its input delay D, s, and ACC share alpha, drawn over the robustness map's ranges; its
discretisation is the caller's) and an initial state: a wave around an equilibrium, either the nominal one (alpha
= 0.15, the paper's) or the plant's own, made of one Fourier mode, a mixture of two, or a localised jam (a Gaussian
bump), with the speed v = q_in / rho (the paper's construction, docs/model.md section 5), and the relative error
of the measurements the laws see (``control.noise.sensor_noise``; none by default).

``sample(dist, split, n, seed)`` draws ``n`` scenarios of ``split`` ("train" or "test") from their own stream
(``jax.random.fold_in`` of the seed with the split's index): the same call gives the same scenarios on every
machine, the two splits are independent draws, and no scenario of one is a scenario of the other (checked:
``Scenarios.key_of`` rows). Training recipes draw from "train" only; the benchmark reports "test".
"""

from __future__ import annotations

import dataclasses
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
from flax import struct

from jaxtraffic.model.params import TrafficParams, equilibrium
from jaxtraffic.sim.batching import stack_params

SPLITS = ("train", "test")
KINDS = ("mode", "mixture", "jam")  # one Fourier mode, two, a localised jam


@dataclasses.dataclass(frozen=True)
class ScenarioDistribution:
    """Where scenarios are drawn from. Units: densities veh/km, delays s, lengths m."""

    delay_range: tuple[float, float] = (0.0, 8.0)  # the plant's input delay D, s (the map's range)
    alpha_range: tuple[float, float] = (0.05, 0.6)  # the plant's ACC share (the map's range)
    amp_range: tuple[float, float] = (5.0, 15.0)  # the wave's amplitude, veh/km (the paper's: 10)
    wavenumbers: tuple[int, ...] = (1, 2, 3, 4, 5, 6)  # waves over the road (the paper's: 4)
    kind_weights: tuple[float, float, float] = (0.5, 0.3, 0.2)  # mode, mixture, jam
    jam_width_range: tuple[float, float] = (30.0, 150.0)  # the jam's standard deviation, m
    own_equilibrium: float = 0.5  # share of waves around the plant's own equilibrium (the rest: the nominal's)
    nominal_alpha: float = 0.15  # the nominal equilibrium's ACC share (the paper's)
    # the relative error of every measurement a law sees (control.noise.sensor_noise: rho (1 + s e), e ~ N(0, 1) per
    # node and step), s drawn per scenario; dimensionless (0.05: 5 %); (0, 0): exact measurements
    sensor_noise_range: tuple[float, float] = (0.0, 0.0)

    def __post_init__(self) -> None:
        for name in ("delay_range", "alpha_range", "amp_range", "jam_width_range", "sensor_noise_range"):
            lo, hi = getattr(self, name)
            if not (np.isfinite(lo) and np.isfinite(hi) and 0 <= lo <= hi):
                raise ValueError(f"{name} must be a finite range 0 <= lo <= hi, got {(lo, hi)}")
        for name in ("alpha_range", "sensor_noise_range"):
            if getattr(self, name)[1] > 1:
                raise ValueError(f"{name} must lie in [0, 1], got {getattr(self, name)}")
        if not self.wavenumbers or min(self.wavenumbers) < 1:
            raise ValueError(f"wavenumbers must be integers >= 1, got {self.wavenumbers}")
        w = np.asarray(self.kind_weights, float)
        if w.shape != (3,) or np.any(w < 0) or w.sum() <= 0:
            raise ValueError(f"kind_weights must be three weights >= 0 (mode, mixture, jam), got {self.kind_weights}")
        if not 0 <= self.own_equilibrium <= 1:
            raise ValueError(f"own_equilibrium must be a share in [0, 1], got {self.own_equilibrium}")


@dataclasses.dataclass(frozen=True)
class Scenarios:
    """``n`` drawn scenarios on one discretisation: ``plants`` (a batched ``TrafficParams``), ``rho0`` (veh/m) and
    ``v0`` (m/s), shapes (n, n_points), and ``draws``: what was drawn, per scenario (recorded with the results)."""

    split: str
    seed: int
    plants: TrafficParams
    rho0: np.ndarray
    v0: np.ndarray
    draws: dict[str, np.ndarray]

    def __len__(self) -> int:
        return int(self.rho0.shape[0])

    def noise_levels(self) -> np.ndarray:
        """(n,): each scenario's sensor noise level (relative standard deviation; 0 where none was drawn)."""
        return np.asarray(self.draws.get("sensor_noise", np.zeros(len(self))), float)

    def keys(self) -> jax.Array:
        """(n, 2): each scenario's PRNG key (its sensor noise), from the split's seed and the scenario's own index: the
        same values in any order and chunk, and for every law and trainer that sees the scenario."""
        return jax.vmap(lambda i: jax.random.fold_in(jax.random.PRNGKey(self.seed), i))(jnp.arange(len(self)))

    def key_of(self) -> np.ndarray:
        """One row per scenario of everything drawn (to compare splits)."""
        return np.stack([np.asarray(v, float) for v in self.draws.values()], axis=1)

    def describe(self) -> dict[str, Any]:
        """The draws as lists (JSON), with their units."""
        return {"split": self.split, "seed": self.seed, "n": len(self),
                "units": {"delay": "s", "amp": "veh/km", "jam_width": "m", "phase": "rad", "alpha": "1",
                          "sensor_noise": "1 (relative standard deviation)"},
                **{k: np.asarray(v).tolist() for k, v in self.draws.items()}}


def _draw(dist: ScenarioDistribution, n: int, key: jax.Array) -> dict[str, np.ndarray]:
    rng = np.random.default_rng(np.asarray(jax.random.key_data(key)).astype(np.uint32))
    w = np.asarray(dist.kind_weights, float)
    return {
        "delay": rng.uniform(*dist.delay_range, n), "alpha": rng.uniform(*dist.alpha_range, n),
        "kind": rng.choice(len(KINDS), n, p=w / w.sum()), "own": rng.uniform(size=n) < dist.own_equilibrium,
        "amp": rng.uniform(*dist.amp_range, n), "amp2": rng.uniform(*dist.amp_range, n),
        "wavenumber": rng.choice(np.asarray(dist.wavenumbers), n),
        "wavenumber2": rng.choice(np.asarray(dist.wavenumbers), n),
        "phase": rng.uniform(0.0, 2 * np.pi, n), "phase2": rng.uniform(0.0, 2 * np.pi, n),
        "jam_centre": rng.uniform(0.2, 0.8, n), "jam_width": rng.uniform(*dist.jam_width_range, n),
        # (drawn last: the draws above are those of a distribution without it)
        "sensor_noise": rng.uniform(*dist.sensor_noise_range, n)}


def initial_states(d: dict[str, np.ndarray], base: TrafficParams, dist: ScenarioDistribution
                   ) -> tuple[np.ndarray, np.ndarray]:
    """(rho0 veh/m, v0 m/s), shapes (n, n_points), of the draws ``d`` on ``base``'s grid (float64)."""
    x = np.asarray(base.x(), float)
    L, q_in = float(base.L), float(base.q_in)
    rho_nom = float(equilibrium(base.replace(alpha=dist.nominal_alpha))[0])
    rows = []
    for i in range(len(d["delay"])):
        rho_bar = float(equilibrium(base.replace(alpha=float(d["alpha"][i])))[0]) if d["own"][i] else rho_nom
        amp = d["amp"][i] * 1e-3
        kind = KINDS[int(d["kind"][i])]
        if kind == "jam":
            wave = amp * np.exp(-0.5 * ((x - d["jam_centre"][i] * L) / d["jam_width"][i]) ** 2)
        else:
            wave = amp * np.cos(2 * np.pi * d["wavenumber"][i] * x / L + d["phase"][i])
            if kind == "mixture":  # two modes, their amplitudes split so that the sum stays within amp's range
                wave = 0.5 * (wave + d["amp2"][i] * 1e-3 * np.cos(2 * np.pi * d["wavenumber2"][i] * x / L
                                                                  + d["phase2"][i]))
        rows.append(rho_bar + wave)
    rho0 = np.stack(rows)
    return rho0, q_in / rho0


def sample(dist: ScenarioDistribution, split: str, n: int, seed: int = 0,
           base: TrafficParams | None = None) -> Scenarios:
    """``n`` scenarios of ``split`` (module docstring) on the discretisation of ``base`` (default: the paper's
    grid), with ``base``'s delay buffer (its ``max_delay_steps`` must hold ``delay_range``'s upper end)."""
    if split not in SPLITS:
        raise ValueError(f"split must be one of {SPLITS}, got {split!r}")
    if not (isinstance(n, int) and n >= 1):
        raise ValueError(f"n must be an int >= 1, got {n!r}")
    base = TrafficParams() if base is None else base
    d = _draw(dist, n, jax.random.fold_in(jax.random.key(seed), SPLITS.index(split)))
    dt = float(base.dt)
    d["delay"] = np.round(d["delay"] / dt) * dt  # whole steps: one buffer read per plant
    if d["delay"].max() > base.max_delay_steps * dt + 1e-9:
        raise ValueError(f"delay_range reaches {d['delay'].max():g} s, beyond the plant's buffer "
                         f"({base.max_delay_steps} steps of {dt:g} s): raise max_delay_steps")
    rho0, v0 = initial_states(d, base, dist)
    if np.any(rho0 <= 0) or np.any(rho0 >= 1 / float(base.l)):
        raise ValueError("a drawn initial state leaves the physical region 0 < rho < 1/l: lower amp_range")
    plants = stack_params(*(base.replace(delay=float(dl), alpha=float(al)) for dl, al in zip(d["delay"], d["alpha"],
                                                                                           strict=True)))
    return Scenarios(split=split, seed=seed, plants=plants, rho0=rho0, v0=v0, draws=d)


@struct.dataclass
class EpisodePool:
    """A finite set of training episodes (``EnvConfig.train_split``: the scenario distribution's train split): per
    scenario the plant's delay D (s) and ACC share alpha, shapes (P,), the initial density (veh/m) and speed
    (m/s), shapes (P, n_points), and the sensor noise a law sees (``Scenarios.noise_levels``, (P,), and
    ``Scenarios.keys``, (P, 2)). A reset draws one uniformly."""

    delay: jax.Array
    alpha: jax.Array
    rho0: jax.Array
    v0: jax.Array
    noise: jax.Array
    keys: jax.Array

    @classmethod
    def train_split(cls, n: int, traffic: TrafficParams, sensor_noise: tuple[float, float] = (0.0, 0.0)
                    ) -> EpisodePool:
        """``n`` scenarios of the train split (``compare.scenarios.sample``, seed 0) on ``traffic``'s grid, each
        seen with a relative sensor error drawn from U(``sensor_noise``): the same scenarios for any range, and for
        a given ``n`` the levels and keys ``compare.tuning`` sees on ``sample(..., "train", n, 0)`` (the draws of
        another ``n`` are other draws, not a subset)."""
        scen = sample(ScenarioDistribution(sensor_noise_range=sensor_noise), "train", n, 0,
                      base=traffic.replace(alpha_noise=0.0))
        dtype = jnp.result_type(float)
        return cls(delay=jnp.asarray(scen.draws["delay"], dtype), alpha=jnp.asarray(scen.draws["alpha"], dtype),
                   rho0=jnp.asarray(scen.rho0, dtype), v0=jnp.asarray(scen.v0, dtype),
                   noise=jnp.asarray(scen.noise_levels(), jnp.float32), keys=scen.keys())

"""Validation of the training config tree (``runs.config.TrainConfig``), in one place.

``check_config(config)`` runs when a ``TrainConfig`` is built (its ``__post_init__``), so a bad value
fails before any directory is created or anything compiles, with a message naming the field, its
the value and the allowed range, e.g. ``lr = -1.0: must be > 0``. It checks every
leaf's type (from its annotation; numpy integers and floats are accepted and normalised to Python
ones, strings and bools where a number is expected are not) and its range (the field's metadata,
``jaxtraffic.fields.hyper``, on the library struct's own field), then the constraints between fields.
``check_devices`` adds what depends on the process (the device count).
The plant's physics (equilibrium, CFL, delay vs buffer) is checked by ``TrafficParams``.
"""

from __future__ import annotations

import dataclasses
import math
import numbers
import os
from collections.abc import Mapping
from typing import Any

from jaxtraffic.fields import check_value, fail

# Every value must survive its conversion to the dtype it is traced as: an int to int32 (unless its own range
# declares a wider one: the seed's uint32), a float to float32 (finite unless its field's metadata says
# ``inf=True``, and not a nonzero value that would round to 0).
FLOAT32_MAX = 3.4028234663852886e38
FLOAT32_TINY = 1.1754943508222875e-38  # the smallest normal float32
INT32_MAX = 2**31 - 1
MAX_STEPS = 10**8  # time steps of one rollout (a longer one would not fit the step counters, nor finish)


def _is_int(x: Any) -> bool:
    return isinstance(x, numbers.Integral) and not isinstance(x, bool) and type(x).__name__ != "bool_"


def _is_real(x: Any) -> bool:
    return isinstance(x, numbers.Real) and not isinstance(x, bool) and type(x).__name__ != "bool_"


def _scalar(name: str, kind: str, value: Any, int_max: int = INT32_MAX, inf: bool = False) -> Any:
    """``value`` checked against the scalar type ``kind`` ("int", "float", "bool", "str") and normalised; an
    integer's magnitude at most ``int_max`` (int32's, or the field's own wider range); ``inf``: a float may be
    inf."""
    if kind == "int":
        if not _is_int(value):
            raise fail(name, value, "must be an integer")
        if abs(int(value)) > int_max:
            raise fail(name, value, f"must fit {'int32' if int_max == INT32_MAX else 'its integer type'}"
                        f" (|x| <= {int_max})")
        return int(value)
    if kind == "float":
        if not _is_real(value):
            raise fail(name, value, "must be a number")
        value = float(value)
        if math.isnan(value) or (math.isinf(value) and not inf):
            raise fail(name, value, "must be finite")
        if math.isfinite(value) and abs(value) > FLOAT32_MAX:  # the programs compute in float32: it would be inf
            raise fail(name, value, f"must be finite in float32 (|x| <= {FLOAT32_MAX:.3g})")
        if value != 0.0 and abs(value) < FLOAT32_TINY:  # float32 would make it 0 (or a denormal)
            raise fail(name, value, f"must be 0 or at least {FLOAT32_TINY:.3g} in magnitude (float32)")
        return value
    if kind == "bool":
        if not isinstance(value, bool) and type(value).__name__ != "bool_":
            raise fail(name, value, "must be true or false")
        return bool(value)
    if kind == "str":
        if not isinstance(value, str):
            raise fail(name, value, "must be a string")
    return value


def _typed(name: str, annotation: str, value: Any, int_max: int = INT32_MAX, inf: bool = False) -> Any:
    """``value`` checked against the field's annotation (as written in ``runs.config.tree``); ``int_max``: the
    largest integer magnitude, ``inf``: inf allowed (``_scalar``)."""
    kind = annotation.replace(" ", "")
    if kind.endswith("|None"):
        if value is None:
            return None
        kind = kind[: -len("|None")]
    one = kind.startswith("float|tuple[")  # one value or a fixed-length tuple of them (gain_max)
    if one:
        kind = "float" if isinstance(value, numbers.Real) else kind[len("float|"):]
    if kind.startswith("tuple["):
        inner = kind[len("tuple["):-1].split(",")
        if isinstance(value, (str, bytes)) or not hasattr(value, "__len__"):
            raise fail(name, value, f"must be a sequence of {inner[0]}s")
        if inner[-1] == "...":  # any length >= 1
            if len(value) < 1:
                raise fail(name, value, f"must hold at least one {inner[0]}")
            return tuple(_scalar(name, inner[0], v, int_max) for v in value)
        if len(value) != len(inner):
            raise fail(name, value, f"must be a pair LO,HI of {inner[0]}s" if len(inner) == 2
                        else f"must be {'one value or ' if one else ''}{len(inner)} {inner[0]}s")
        return tuple(_scalar(name, k, v, int_max) for k, v in zip(inner, value, strict=True))
    if kind in ("int", "float", "bool", "str"):
        return _scalar(name, kind, value, int_max, inf)
    return value  # an annotation this module does not know: left to its owner


def _check_pair(name: str, value: tuple | None, bounds: tuple | None) -> None:
    """A LO,HI pair: LO <= HI, both within ``bounds`` (lo bound, hi bound or None; its field's ``pair``)."""
    if bounds is None or value is None:
        return
    lo_bound, hi_bound = bounds
    lo, hi = value
    if lo > hi:
        raise fail(name, value, "needs LO <= HI")
    if lo < lo_bound or (hi_bound is not None and hi > hi_bound):
        span = f"[{lo_bound}, {hi_bound}]" if hi_bound is not None else f">= {lo_bound}"
        raise fail(name, value, f"both ends must be {span}" if hi_bound is None else f"must lie in {span}")


def _checked(f: dataclasses.Field, value: Any) -> Any:
    """``value`` of the field ``f`` checked (type, choices, range, pair bounds) and normalised."""
    rule = f.metadata.get("range")
    wide = rule[2] if rule is not None and rule[2] is not None and rule[2] > INT32_MAX else INT32_MAX  # (the seed)
    try:
        typed = _typed(f.name, str(f.type), value, int(wide), bool(f.metadata.get("inf")))
    except ValueError:  # the field's own range says more than the dtype's (max_delay_steps: [0, 1000000])
        if rule is not None and rule[2] is not None and _is_int(value):
            check_value(f.name, value, rule)
        raise
    choices = f.metadata.get("choices")
    if choices and typed is not None and typed not in choices:
        raise fail(f.name, typed, f"must be one of {tuple(choices)}")
    if isinstance(typed, tuple) and rule is None:  # LO,HI pairs
        _check_pair(f.name, typed, f.metadata.get("pair"))
    else:  # a number, or each element of a tuple (gain_max, the scenario grids)
        check_value(f.name, typed, rule)
    return typed


def check_table(cls: type, table: Mapping[str, Any]) -> dict[str, Any]:
    """The values ``table`` gives fields of the dataclass ``cls``, checked and normalised (before ``cls`` is
    built: a library struct's own checks then see clean values)."""
    fields = {f.name: f for f in dataclasses.fields(cls)}
    return {k: _checked(fields[k], v) if k in fields else v for k, v in table.items()}


def check_section(section: Any) -> None:
    """Check (and normalise in place: numpy scalars to Python ones, lists to tuples) one frozen
    config dataclass: every field's type, range and pair bounds."""
    for f in dataclasses.fields(section):
        value = getattr(section, f.name)
        typed = _checked(f, value)
        if typed is not value:
            object.__setattr__(section, f.name, typed)


def check_config(config: Any) -> None:
    """Check a whole ``TrainConfig``: each section, then the constraints between fields."""
    for f in dataclasses.fields(config):  # plant, env, algo, run and any other section
        check_section(getattr(config, f.name))
    pl, en, al, run = config.plant, config.env, config.ppo, config.run
    if not run.out_dir:
        raise fail("out_dir", run.out_dir, "must not be empty")
    batch = al.num_envs * al.num_steps
    if run.algo == "ppo" and batch % al.num_minibatches:  # (PPO's rules do not block a gradient run)
        raise fail("num_minibatches", al.num_minibatches,
                    f"must divide the batch num_envs * num_steps = {al.num_envs} * {al.num_steps} = {batch}")
    if run.algo == "ppo" and al.num_minibatches > batch:
        raise fail("num_minibatches", al.num_minibatches, f"must be <= the batch num_envs * num_steps = {batch}")
    cp = config.grad.controller_points
    if cp and (cp > pl.n_points or (pl.n_points - 1) % (cp - 1)):
        raise fail("controller_points", cp, f"the plant's grid (n-points {pl.n_points}) must refine it by an integer "
                    f"factor: (n_points - 1) a multiple of (controller_points - 1)")
    if cp and cp != pl.n_points and run.algo != "gradient":
        raise fail("controller_points", cp, "PPO's controller acts on the training plant's grid; only `train.py "
                    "gradient` trains a controller on a grid of its own")
    if en.train_sensor_noise[1] > 0 and not en.train_split:  # (the scenarios' levels and keys are the split's)
        raise fail("train_sensor_noise", en.train_sensor_noise, "needs --train-split N > 0: the train split's "
                   "scenarios carry the noise levels and keys the comparison sees (and selects checkpoints on)")
    if run.val_plant == "reference" and run.val_horizon_s > 0 and run.algo == "ppo":
        _check_reference_validation(pl)
    for name in ("horizon_s", "eval_horizon_s"):
        value = getattr(en if name == "horizon_s" else run, name)
        if value < pl.dt:
            raise fail(name, value, f"must be >= one time step dt = {pl.dt} s")
    for name, section in (("horizon_s", en), ("eval_horizon_s", run), ("val_horizon_s", run),
                          ("train_horizon_s", config.grad)):
        if (getattr(section, name) or 0.0) / pl.dt > MAX_STEPS:
            raise fail(name, getattr(section, name), f"must be at most {MAX_STEPS:.0e} time steps of dt = {pl.dt} s")
    _check_grid(config)


def _check_grid(config: Any) -> None:
    """Values absurd for the plant's grid: an initial wavenumber above its Nyquist limit ((n_points - 1) / 2
    periods on the road: the cosine would alias), a rollout of more than ``MAX_STEPS`` solver steps
    (time steps x ``substeps``)."""
    pl, ppo = config.plant, config.run.algo == "ppo"  # (only the algorithm's own fields: the others' defaults
    nyquist = (pl.n_points - 1) // 2                   # need not suit a coarse grid)
    name, values = (("wavenumber_range", config.env.wavenumber_range) if ppo
                    else ("train_wavenumbers", config.grad.train_wavenumbers))
    if any(abs(k) > nyquist for k in values):
        raise fail(name, tuple(values), f"must be at most the grid's Nyquist limit (n_points - 1) / 2 = "
                    f"{nyquist} periods on the road (n_points {pl.n_points})")
    horizons = (config.env.horizon_s, config.run.val_horizon_s) if ppo else (config.grad.train_horizon_s,)
    steps = max(config.run.eval_horizon_s, *horizons) / pl.dt
    if pl.substeps > 1 and steps * pl.substeps > MAX_STEPS:
        raise fail("substeps", pl.substeps, f"{steps:.0f} time steps of the longest rollout x substeps must be at "
                    f"most {MAX_STEPS:.0e} solver steps")


def _check_reference_validation(pl: Any) -> None:
    """The validation suite on the reference plant needs its grid to refine the training grid and its CFL
    bound at the training dt."""
    from jaxtraffic.model.params import TrafficParams

    ref = TrafficParams.reference()
    if (ref.n_points - 1) % (pl.n_points - 1):
        raise fail("n_points", pl.n_points, f"the validation suite runs on the reference plant ({ref.n_points} "
                    f"points), whose grid must refine the training grid by an integer factor: n_points - 1 must "
                    f"divide {ref.n_points - 1} (or give --val-plant training)")
    try:
        ref.replace(dt=pl.dt, max_delay_steps=pl.max_delay_steps)
    except ValueError as err:
        raise fail("val_plant", "reference", f"the reference plant at dt = {pl.dt} s: {err} (or give --val-plant "
                    "training)") from None


def check_devices(config: Any, n_devices: int) -> None:
    """The constraints that depend on the number of devices the environments are split over."""
    al = config.ppo
    if al.num_envs % n_devices:
        raise fail("num_envs", al.num_envs, f"must be divisible by the number of devices ({n_devices})")
    local = al.num_envs // n_devices * al.num_steps
    if local % al.num_minibatches:
        raise fail("num_minibatches", al.num_minibatches,
                    f"must divide the batch of each device, num_envs / devices * num_steps = {local}")


# Measured on a 2-core CPU (peak RSS less the bare process's, 2026-12-05, benchmarks/memory_check.py): max_delay_steps
# 50 000 on 201 points: 3.2 GiB against 4.9 estimated; hidden (4000, 4000): 4.3 GiB, 33 copies of the parameters.
CARRY_COPIES = 2  # a lax.scan's carry lives twice (the step's input and output) while a step runs
NETWORK_COPIES = 36  # training (parameters, gradients, Adam's moments), the suite's per-scenario repeat, checkpoints


def memory_estimate(config: Any) -> dict[str, float]:
    """The bytes PPO's programs hold (float32), by what holds them: the training environments (fields and delay
    buffer, ``CARRY_COPIES``), one update's rollout, the evaluation rollouts (one per member), the validation suite
    (its scenarios on the judging plant, the reference plant's grid by default, with their delay buffers and the
    policy's own buffer of sent fields, and backstepping's reference rollouts), and the networks (``NETWORK_COPIES``
    per member, and the activations of a minibatch forward and backward)."""
    from jaxtraffic.control.gain_policy import feature_size
    from jaxtraffic.control.networks import actor_critic_size
    from jaxtraffic.model.params import REFERENCE_POINTS

    pl, al, run = config.plant, config.ppo, config.run
    n, cap, members = pl.n_points, pl.max_delay_steps + 1, al.num_seeds
    env_state = (cap + 6) * n
    envs = al.num_envs * members
    d_in = feature_size(n, config.env.obs_segments)
    parts = {"training environments": CARRY_COPIES * envs * env_state,
             "one update's rollout": envs * al.num_steps * (2 * (d_in + 3) + 12),
             "evaluation rollouts": CARRY_COPIES * members * env_state,
             "networks": NETWORK_COPIES * members * actor_critic_size(d_in, al.hidden)
             + 3 * envs * al.num_steps // al.num_minibatches * 2 * sum(al.hidden)}
    if run.val_horizon_s > 0:
        judge = REFERENCE_POINTS if run.val_plant == "reference" else n
        scenarios = 3 * 2  # the validation delays (at most 3) and its two initial waves (runs.ppo.selection)
        parts["validation suite"] = CARRY_COPIES * scenarios * (members + 1) * ((cap + 6) * judge + cap * n)
    return {k: 4.0 * v for k, v in parts.items()}


def check_memory(config: Any, have: float | None = None) -> None:
    """PPO's programs must fit this machine's memory (``have`` bytes; default: the physical memory)."""
    need = memory_estimate(config)
    refuse_memory(need, have, "num_envs", config.ppo.num_envs,
                  f"with num_steps = {config.ppo.num_steps}, {config.ppo.num_seeds} seed(s), max_delay_steps = "
                  f"{config.plant.max_delay_steps} on {config.plant.n_points} points and hidden = "
                  f"{tuple(config.ppo.hidden)}", "use fewer environments, steps, a smaller delay buffer or network")


def refuse_memory(need: dict[str, float], have: float | None, field: str, value: Any, what: str, advice: str) -> None:
    """``fail(field, value, ...)`` if the bytes ``need`` (by component) exceed 80 % of ``have`` (default: this
    machine's physical memory), naming the largest component."""
    if have is None:
        try:
            have = float(os.sysconf("SC_PHYS_PAGES") * os.sysconf("SC_PAGE_SIZE"))
        except (ValueError, OSError, AttributeError):
            return
    total = sum(need.values())
    if total > 0.8 * have:
        big = max(need, key=lambda k: need[k])
        raise fail(field, value, f"{what}: the run needs about {total / 2**30:.3g} GiB ({big}: "
                                 f"{need[big] / 2**30:.3g} GiB), more than this machine's {have / 2**30:.3g} GiB; "
                                 f"{advice}")


def check_initial_amplitudes(config: Any, traffic: Any) -> None:
    """Every PPO episode must start inside the physical region: both ends of ``amp_range`` (veh/km) on
    ``traffic`` (concrete ``TrafficParams``)."""
    from jaxtraffic.model.solver import is_physical
    from jaxtraffic.sim.initial import paper_initial_condition
    from jaxtraffic.sim.metrics import VEH_PER_KM

    en = config.env
    for amp in en.amp_range:
        rho0, v0 = paper_initial_condition(traffic, amp / VEH_PER_KM, float(en.wavenumber_range[0]))
        if not bool(is_physical(rho0, v0, traffic)):
            raise fail("amp_range", tuple(en.amp_range), f"an initial state of amplitude {amp:g} veh/km leaves the "
                        "physical region (0 < rho < 1/l, v >= 0); use smaller amplitudes")

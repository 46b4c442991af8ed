"""One config tree for training: the library's configs nested as they are, and the run's own.

    plant  model.params.TrafficParams    the nominal training plant and its grid
    env    learn.env_config.EnvConfig    episodes, domain randomisation, reward shaping, observation
    ppo    learn.ppo.PPOConfig           PPO (num_seeds: the population)
    grad   learn.gradient.config.GradientConfig the gradient and CEM trainers
    run    RunConfig (here)              where, how long, the stop rule

Each setting is a field of the one dataclass that uses it, with its default, range and help text there; a
section is built with ``TrainConfig.make(plant={...}, ...)``, read with ``config.tables()``.
``train.py``'s flags are derived from the fields by tyro (``cli.train``: one flag per leaf field that the
algorithm reads, ``fields_for``, named after it, with the one-line ``help`` of its metadata; a longer explanation
is the comment above the field). A run's files (config.toml, its truth, and config.json, the machine copy) are
written and read by ``runs.config.toml``.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

from jaxtraffic.fields import hyper
from jaxtraffic.learn.env import PLANT, EnvParams, env_params
from jaxtraffic.learn.env_config import EnvConfig
from jaxtraffic.learn.gradient.config import GradientConfig
from jaxtraffic.learn.ppo import PPOConfig
from jaxtraffic.model.params import TrafficParams
from jaxtraffic.sim.metrics import REWARD_TARGET

# 4: the plant section is TrafficParams, controller_points the gradient trainer's; 5: the initial amplitudes in veh/km;
# 6: train_sensor_noise the environment's (both trainers') (toml.MIGRATIONS)
CONFIG_VERSION = 6


ALGOS = ("ppo", "gradient")
# The default PPO recipe is a population (docs/model.md section 13.8, "Why a population"): POPULATION members
# trained at once, each on PPOConfig's num_envs / POPULATION environments, so that a chunk steps as many
# environments as one member of PPOConfig's size; the run stops on the first member that meets the rule.
POPULATION = 2


@dataclass(frozen=True)
class RunConfig:
    """Run control: where, how long, the stop rule. ``RUN_CONTROL`` fields may change on resume."""

    algo: str = hyper("ppo", help="ppo or gradient (train.py's subcommand)", choices=ALGOS, cli=False)
    out_dir: str = hyper("runs/default", help="run directory (gradient: runs/gradient-POLICY)")
    # continue from the run directory's checkpoint with its saved config, run control included; the RUN_CONTROL
    # flags given with it (gradient: also grad_steps) apply and are recorded, any other change is an error
    resume: bool = hyper(False, help="continue the run in --out-dir")
    # a fresh run into an out_dir holding another run's results (checkpoint, best policy, summary, learning
    # curve) clears them first; without it that is an error
    overwrite: bool = hyper(False, help="clear the run in --out-dir first")
    seed: int = hyper(0, help="PRNG seed", lo=0, hi=2**32 - 1)
    total_steps: int = hyper(10_000_000, help="environment steps per member", lo=1, algo="ppo")
    max_wall_s: float = hyper(math.inf, help="stop after this many seconds", lo=0.0, lo_open=True, inf=True)
    keep_going: bool = hyper(False, help="ignore the stop rule", algo="ppo")
    # stop rule: the deterministic evaluation reward (end of the evaluation rollout) >= this
    target_reward: float = hyper(REWARD_TARGET, help="stop rule: evaluation reward >= this", algo="ppo")
    # the stop rule also requires the closed loop's kinematic wave speed at the policy's equilibrium gains
    # (linear.gain_law_wave_speed) >= this; None (-inf on the command line): the paper's rule alone
    min_wave_speed: float | None = hyper(0.5, help="stop rule: wave speed >= this, m/s (-inf: off)", algo="ppo")
    # the stop rule also requires the stability certificate (control.stability) of the policy's equilibrium
    # gains at the training delay and alpha: largest growth rate over wavenumbers <= 1e-3/s
    require_certificate: bool = hyper(True, help="stop rule: the stability certificate", algo="ppo")
    # consecutive evaluations that must meet the stop rule (per population member) before stopping
    stop_patience: int = hyper(1, help="stop rule: consecutive evaluations", lo=1, algo="ppo")
    # a member that has not met the stop rule this many env steps after its start is re-initialised from a new
    # key (its best checkpoint is kept); 0: never (also with keep_going)
    restart_steps: int = hyper(1_500_000, help="restart a member after these steps (0: never)", lo=0, algo="ppo")
    # validation suite (runs.ppo.selection): each member's policy on 2 initial states x 3 training delays, scored
    # against backstepping; each member's best checkpoint is kept (best.msgpack), the best member is the policy
    val_horizon_s: float = hyper(600.0, help="validation suite length, s (0: none)", lo=0.0, algo="ppo")
    # the plant the validation suite runs on: reference (TrafficParams.reference: MUSCL, 801 points, 2 solver
    # steps; the policy acts on its training grid through control.adapter) or training (the training plant)
    val_plant: str = hyper("reference", help="validation suite's plant", choices=("reference", "training"), algo="ppo")
    # 1: at the nominal delay the density L2 at half the suite horizon below backstepping's, J_comfort within
    # 20 % of its, and no delay of the suite diverging or still growing; inf: no such condition
    val_target: float = hyper(1.0, help="stop rule: validation score <= this", lo=0.0, lo_open=True, algo="ppo",
                              inf=True)
    eval_horizon_s: float = hyper(300.0, help="evaluation rollout length, s", lo=0.0, lo_open=True)
    # also after a session's first chunk, at the end and on SIGINT/SIGTERM; SIGKILL loses at most this many chunks
    checkpoint_every: int = hyper(10, help="chunks between checkpoints", lo=1, algo="ppo")
    quiet: bool = hyper(False, help="no progress lines")
    # also write the learning-curve rows as TensorBoard scalars (needs tensorboardX: pip install 'jaxtraffic[tb]')
    tensorboard: str | None = hyper(None, help="TensorBoard log directory")
    # also log the learning-curve rows and the config to an MLflow run (needs mlflow: pip install 'jaxtraffic[mlflow]'):
    # a directory (its SQLite store mlflow.db, offline) or an MLflow tracking URI
    mlflow: str | None = hyper(None, help="MLflow tracking store: a directory or a URI")


RUN_CONTROL = ("out_dir", "total_steps", "max_wall_s", "keep_going", "resume", "overwrite", "quiet", "stop_patience",
               "target_reward", "min_wave_speed", "require_certificate", "tensorboard", "mlflow", "val_target",
               "checkpoint_every")


def run_control(algo: str) -> dict[str, tuple[str, ...]]:
    """The fields a resume may change, by section: ``RUN_CONTROL``, and for the gradient trainer its step count."""
    return {"run": RUN_CONTROL, **({"grad": ("grad_steps",)} if algo == "gradient" else {})}


@dataclass(frozen=True)
class TrainConfig:
    """The whole training configuration: ``plant`` (the library's ``TrafficParams`` as it is: the training plant
    and its grid), ``env`` (``learn.env_config.EnvConfig``), ``ppo`` (the library's ``PPOConfig`` as it is:
    ``num_seeds`` is the population, ``num_envs`` each member's), ``grad`` (gradient-based training) and ``run``."""

    plant: TrafficParams = PLANT  # the environment's default nominal plant (learn.env)
    env: EnvConfig = EnvConfig()
    ppo: PPOConfig = PPOConfig(num_envs=PPOConfig.num_envs // POPULATION, num_seeds=POPULATION)
    grad: GradientConfig = GradientConfig()
    run: RunConfig = RunConfig()

    def __post_init__(self) -> None:
        from jaxtraffic.runs.config.checks import check_config  # every field's type and range (ValueError)
        check_config(self)
        # the gradient trainer's filter and network are the environment's and PPO's (one value each)
        object.__setattr__(self, "grad", dataclasses.replace(
            self.grad, hidden=tuple(self.ppo.hidden), gain_filter=self.env.gain_filter,
            filter_sigma=self.env.filter_sigma, train_split=self.env.train_split,
            train_sensor_noise=self.env.train_sensor_noise))

    @classmethod
    def make(cls, **tables: Mapping[str, Any]) -> TrainConfig:
        """A config from one mapping per section, the rest their defaults (``TrainConfig.make(plant={"n_points":
        21}, ppo={"num_envs": 64})``; the gradient section's defaults are its policy's); an unknown section or
        field is a ``TypeError``."""
        from jaxtraffic.runs.config.checks import check_table  # (checks imports this module)

        for s, table in tables.items():
            if s not in SECTIONS:
                raise TypeError(f"unknown config section {s!r} (the sections are {', '.join(SECTIONS)})")
            unknown = sorted(set(table) - {f.name for f in leaf_fields(s)})
            if unknown:
                raise TypeError(f"the config section {s!r} has no field {unknown[0]!r}")
        # each value's type and range before a section is built (a library struct checks its own values too)
        tables = {s: check_table(SECTIONS[s], table) for s, table in tables.items()}
        grad = GradientConfig.for_policy(**tables.get("grad", {}))  # the policy's defaults under the given fields
        return cls(grad=grad, **{s: dataclasses.replace(_DEFAULT[s], **tables.get(s, {})) for s in SECTIONS
                                 if s != "grad"})

    def tables(self) -> dict[str, dict[str, Any]]:
        """Every section's own fields (``leaf_fields``): ``{section: {field: value}}``, as a config file's tables."""
        return {s: {f.name: getattr(getattr(self, s), f.name) for f in leaf_fields(s)} for s in SECTIONS}

    def updated(self, **tables: Mapping[str, Any]) -> TrainConfig:
        """A copy with the given fields of the given sections changed (``config.updated(run={"seed": 3})``)."""
        own = self.tables()
        for s in tables:
            if s not in own:
                raise TypeError(f"unknown config section {s!r} (the sections are {', '.join(SECTIONS)})")
        return TrainConfig.make(**{s: {**own[s], **tables.get(s, {})} for s in SECTIONS})

    def defaults(self) -> TrainConfig:
        """The defaults of this config's algorithm and gradient policy (what a config file need not say)."""
        return TrainConfig.make(run={"algo": self.run.algo}, grad={"policy": self.grad.policy})

    def env_params(self) -> EnvParams:
        """The environment's parameters (``learn.env.env_params`` of the env section around the plant)."""
        return env_params(self.env, self.plant)


SECTIONS = {"plant": TrafficParams, "env": EnvConfig, "ppo": PPOConfig, "grad": GradientConfig, "run": RunConfig}
# GradientConfig's fields that a run sets from other sections (``TrainConfig.__post_init__``), or not at all
# (max_grad_norm: PPO's field of that name is the flag's)
BORROWED = ("hidden", "gain_filter", "filter_sigma", "max_grad_norm", "train_split", "train_sensor_noise")


def leaf_fields(section: str) -> list[dataclasses.Field]:
    """The fields of a section that are its own (a flag each): all but the gradient section's ``BORROWED``."""
    return [f for f in dataclasses.fields(SECTIONS[section]) if section != "grad" or f.name not in BORROWED]


_DEFAULT: dict[str, Any] = {f.name: f.default for f in dataclasses.fields(TrainConfig)}  # section -> its default
SECTION_ALGO = {"ppo": "ppo", "grad": "gradient"}  # the sections one algorithm reads


def fields_for(algo: str) -> list[tuple[str, dataclasses.Field]]:
    """(section, field) of each leaf field the algorithm ``algo`` reads that is set on the command line
    (``cli.train``): a field with a ``help`` text, but ``cli`` False (a config file's only), whose metadata
    ``algo`` ("ppo", "gradient", "both"; default: its section's) names ``algo``. (The plant's physical constants
    have no help text: they are set in a config file's [plant] table.)"""
    return [(s, f) for s in SECTIONS for f in leaf_fields(s) if f.metadata.get("cli", "help" in f.metadata)
            and f.metadata.get("algo", SECTION_ALGO.get(s, "both")) in ("both", algo)]


def flag_sections(algo: str) -> dict[str, str]:
    """The section of each of ``train.py ALGO``'s flags, by field name (a flag is named after its field, so the
    names of one algorithm's fields are unique across its sections)."""
    owner: dict[str, str] = {}
    for s, f in fields_for(algo):
        if f.name in owner:
            raise RuntimeError(f"two config fields named {f.name!r} ({owner[f.name]}, {s}) would be one flag")
        owner[f.name] = s
    return owner


def flag_tables(algo: str, values: Mapping[str, Any]) -> dict[str, dict[str, Any]]:
    """``values`` given by flag name (``train.py ALGO``'s flags, or the Gymnasium environment's keywords) as
    config tables, ``{section: {field: value}}``; an unknown name is a ``TypeError``."""
    section = flag_sections(algo)
    unknown = sorted(set(values) - set(section))
    if unknown:
        raise TypeError(f"{unknown[0]!r} is not a field of train.py {algo}'s flags")
    tables: dict[str, dict[str, Any]] = {}
    for k, v in values.items():
        tables.setdefault(section[k], {})[k] = v
    return tables

"""The held-out comparison (docs/model.md section 20), as the main job and ``benchmarks/fair_benchmark.py`` run it:
every registered law (``paper.laws``) on the scenario distribution's test split, one plant at a time, over 600 s.

The rows: each model-based law of the registry as the paper has it (``backstepping``: k = 1, pointwise, told each
plant's D; a law registered as told "delay_alpha" is told its alpha too), the predictor laws again with the learned
laws' 25 m measurement filter (``<law>_f25``), the ``TUNABLE`` laws with their parameters tuned on the train split
(``<law>_tuned``: ``benchmarks/tune_baselines.py``'s JSON), the learned laws as the main job trains them (on the
paper's wave: their names), and those trained on the train split over seeds (``<law>_split_s<seed>``:
``benchmarks/train_split_sweep.py``). ``tables`` gives the Markdown table and the held-out checks
(``compare.verdicts``); ``run`` writes ``OUT/fair/<plant>.json`` and ``.md``.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from jaxtraffic.compare import LawSpec, ScenarioDistribution, evaluate_laws, sample, summary_table, verdicts
from jaxtraffic.compare.stats import UNITS
from jaxtraffic.control import Controller, measurement_filter, takes_delay
from jaxtraffic.control.adapter import ControllerGrid
from jaxtraffic.io.files import atomic_write_text, read_json, write_json
from jaxtraffic.io.provenance import provenance
from jaxtraffic.model.params import TrafficParams
from jaxtraffic.paper import laws

SPLIT = "_split_s"  # a split-trained run's row: <law>_split_s<seed>
REFERENCE = "backstepping"  # the row every table's ratio column is taken to (so every judged table has it)
BASES = {"grad_residual": "adaptive_backstepping"}  # a learned law on a model-based base: held out, not worse
HORIZON_S = 600.0  # s, the comparison's horizon (the paper's 300 s snapshot is the paper's column only)
N_TEST = 256  # test scenarios per plant
N_OTHER = 64  # test scenarios on each plant after the main job's first (the reference plant costs ~8x per scenario)


def _given(ctrl: Controller) -> Callable[[], Controller]:
    """A builder that returns ``ctrl``."""
    return lambda: ctrl


def _filtered(build: Callable[[], Controller]) -> Callable[[], Controller]:
    """A builder of ``build``'s law acting on the learned laws' 25 m filtered measurement."""
    return lambda: measurement_filter(build(), laws.FILTER_M)


def model_based(tuned: dict[str, Any] | None = None) -> list[LawSpec]:
    """The registry's model-based laws, the predictor laws with the 25 m filter, and the tuned ones (``tuned``:
    ``tune_baselines.py``'s JSON)."""
    specs = []
    for name in laws.names(learned=False):
        law = laws.LAWS[name]
        assert law.build is not None  # (model-based)
        specs.append(LawSpec(name, law.label, law.build, law.told))
        if law.predictor and law.told == "delay":
            specs.append(LawSpec(f"{name}_f25", f"{law.label}, {laws.FILTER_M:g} m filter",
                                 _filtered(law.build), law.told))
    for name, entry in ((tuned or {}).get("laws") or {}).items():
        t, p = laws.TUNABLE[name], entry["best"]
        text = ", ".join(f"{n} {p[n]:.2f}" for n in t.names)
        specs.append(LawSpec(f"{name}_tuned", f"{laws.label(name)}, tuned ({text}, {laws.FILTER_M:g} m filter)",
                             _given(t.build(laws.CTRL_DELAY, *(p[n] for n in t.names))), "delay"))
    return specs


def learned(controllers: dict[str, Controller], grids: dict[str, ControllerGrid], suffix: str = " (main job's run)"
            ) -> list[LawSpec]:
    """The main job's learned laws (``controllers`` by registry name, acting on ``grids``), then the controllers
    the registry does not know (a user's ``--controller``), under their own names."""
    names = [n for n in laws.names(learned=True) if n in controllers] + [n for n in controllers if n not in laws.LAWS]
    return [LawSpec(n, f"{laws.short_label(n)}{suffix if n in laws.LAWS else ''}", _given(controllers[n]),
                    "delay" if takes_delay(controllers[n]) else "nothing", grids.get(n)) for n in names]


def split_runs(root: Path) -> list[LawSpec]:
    """The learned laws trained on the train split, ``root/<law>/seed<S>`` (``train_split_sweep.py``)."""
    from jaxtraffic.runs.policy import load_policy, policy_grid

    out = []
    for n in laws.names(learned=True):
        for run in sorted((root / n).glob("seed*")):
            if (run / "summary.json").exists():
                ctrl, config = load_policy(run)
                noise = config.env.train_sensor_noise
                seen = f" (sensor noise U({noise[0]:g}, {noise[1]:g}))" if noise[1] > 0 else ""
                out.append(LawSpec(f"{n}{SPLIT}{run.name[4:]}", f"{laws.short_label(n)}, train split{seen}, seed "
                                   f"{run.name[4:]}", _given(ctrl), "delay" if takes_delay(ctrl) else "nothing",
                                   policy_grid(config)))
    return out


def law_of(row: str) -> str:
    """The registered law a row belongs to (its name before a ``_f25``, ``_tuned`` or split-seed suffix)."""
    for suffix in (SPLIT, "_f25", "_tuned"):
        row = row.split(suffix)[0]
    return row


def _kind(row: str) -> str:
    """"learned" or "model" (a registered law's row), "user" (a ``--controller``: in the table, not the frontier)."""
    law = laws.LAWS.get(law_of(row))
    return "user" if law is None else "learned" if law.learned else "model"


def tables(res: dict[str, dict[str, np.ndarray]], labels: dict[str, str]) -> tuple[list[str], dict, dict]:
    """(Markdown lines, summaries, checks): the table, then each split-trained law over its seeds, each law built on
    a base law against it, and the frontier: the best learned law (a split-trained law's median seed; without any,
    the paper-wave rows) against the best model-based row that is told no more than D (the information bound is a
    bound, not a competitor)."""
    lines, summ = summary_table(res, labels, reference=REFERENCE)
    label = labels.__getitem__
    groups = verdicts.seed_groups(list(res), SPLIT)
    seeds, over_seeds = verdicts.seed_lines(res, groups, laws.short_label)
    based, checks = verdicts.base_checks(res, BASES, law_of, label)
    wave = [k for k in res if _kind(k) == "learned" and SPLIT not in k]
    candidates = [verdicts.median_seed(res, rows) for rows in groups.values()] or wave
    # the model-based competitors: not the information bound (told the plant's alpha, which no learned law is told)
    rivals = [k for k in res if _kind(k) == "model" and laws.LAWS[law_of(k)].told != "delay_alpha"]
    front, best = verdicts.frontier(res, candidates, rivals, label)
    checks.update(best, seeds=over_seeds)
    return [*lines, "", "Held-out checks:", "", *seeds, *based, *front], summ, checks


def run(specs: list[LawSpec], plant: str, base: TrafficParams, out_dir: Path | None, n: int = N_TEST,
        horizon_s: float = HORIZON_S, seed: int = 0, log: Callable[[str], None] = print,
        dist: ScenarioDistribution | None = None, name: str | None = None) -> dict[str, Any]:
    """Every law of ``specs`` on ``n`` test scenarios (seed ``seed``) of ``dist`` (default: the default
    distribution) on ``base`` (named ``plant``); writes ``out_dir/<name>.json`` and ``.md`` (default name: the
    plant's) when ``out_dir`` is given; returns the JSON. ``specs`` must hold the reference row (``REFERENCE``).
    Raises:
        ValueError: before anything runs, without the reference row."""
    if REFERENCE not in {s.name for s in specs}:
        raise ValueError(f"the rows must include {REFERENCE!r}: every table's ratios are taken to it")
    scen = sample(dist or ScenarioDistribution(), "test", n, seed, base=base)
    name = name or plant
    res = evaluate_laws(specs, scen, base, horizon_s, log=log)
    labels = {s.name: s.label for s in specs}
    lines, summ, checks = tables(res, labels)
    out = {"plant": plant, "horizon_s": horizon_s, "laws": labels, "summary": summ, "checks": checks,
           "per_scenario": {k: {m: _float32_list(v) for m, v in r.items()} for k, r in res.items()},
           "scenarios": scen.describe(), "provenance": provenance(), "markdown": lines}
    if out_dir is not None:
        write_json(out_dir / f"{name}.json", out)
        atomic_write_text(out_dir / f"{name}.md", "\n".join(lines) + "\n")
    return out


def _float32_list(values: Any) -> list:
    """A measure's per-scenario values as a JSON list at the precision they were computed in (float32: 7
    significant digits, not float64's 17 of the same number); booleans as they are."""
    a = np.asarray(values)
    if a.dtype == bool:
        return a.tolist()
    return [float(f"{x:.7g}") for x in a.astype(float).tolist()]


def resummarise(path: Path) -> list[str]:
    """Rewrite the table, summaries and checks of an earlier run's JSON from its per-scenario measures (nothing
    simulated; its provenance kept, the code that summarised it as ``summarised_by``); returns the lines."""
    d = read_json(path)
    if not isinstance(d.get("per_scenario"), dict):
        raise ValueError(f"{path} holds no per-scenario measures ({d.get('per_scenario')!r}); rerun the benchmark")
    res = {k: {m: np.asarray([np.inf if x is None else x for x in v], float) if m not in ("diverged", "not_settled")
               else np.asarray(v, bool) for m, v in r.items()} for k, r in d["per_scenario"].items()}
    lines, d["summary"], d["checks"] = tables(res, d["laws"])
    d["markdown"], d["summarised_by"] = lines, provenance()
    write_json(path, d)
    atomic_write_text(path.with_suffix(".md"), "\n".join(lines) + "\n")
    return lines


@dataclasses.dataclass(frozen=True)
class FairStage:
    """The held-out comparison as a stage of the main job (``evaluate.py``): ``n`` test scenarios on its first plant
    and ``n_other`` on each other plant (0: skipped there), the model-based laws' ``tuned`` parameters
    (``tune_baselines.py``'s JSON; None: no tuned rows) and the ``split_root`` of learned runs trained on the train
    split (None: none)."""

    n: int = N_TEST
    tuned: dict[str, Any] | None = None
    split_root: Path | None = None
    n_other: int = N_OTHER

    @classmethod
    def from_paths(cls, n: int, tuned: Path | None, split_root: Path | None, n_other: int = N_OTHER) -> FairStage:
        """The stage of ``n`` (``n_other``) scenarios with the tuned parameters of the JSON ``tuned`` (when that
        file exists)."""
        for flag, value in (("--fair", n), ("--fair-other", n_other)):
            if value < 0:
                raise ValueError(f"{flag} must be >= 0 test scenarios (0: skip the comparison), got {value}")
        if split_root is not None and not split_root.is_dir():
            raise ValueError(f"--split-runs {split_root}: not a folder (benchmarks/train_split_sweep.py --out)")
        return cls(n, read_json(tuned) if tuned is not None and tuned.exists() else None, split_root, n_other)

    def scenarios(self, first: bool) -> int:
        """The test scenarios on the main job's first plant (``first``) or on another one."""
        return self.n if first else self.n_other

    def section(self, controllers: dict[str, Controller], grids: dict[str, ControllerGrid], plant: str,
                base: TrafficParams, out_dir: Path | None, n: int, log: Callable[[str], None] = print) -> list[str]:
        """Run it on ``n`` scenarios of ``base`` (named ``plant``; ``run``, files in ``out_dir``) and return
        REPORT.md's section."""
        specs = (model_based(self.tuned) + learned(controllers, grids)
                 + (split_runs(self.split_root) if self.split_root else []))
        log(f"== held-out comparison: {len(specs)} laws x {n} test scenarios x {HORIZON_S:g} s ({plant} plant)")
        out = run(specs, plant, base, out_dir, n, log=log)
        return [f"## Held-out comparison (the test split, {plant} plant)", "",
                f"Every law on {n} scenarios of the scenario distribution's test split (docs/model.md section "
                f"20) on the {plant} plant, {HORIZON_S:g} s: median [bootstrap 95 % interval] over the scenarios. "
                f"J_comfort in {UNITS['J_comfort']}. The learned laws are this job's runs; those trained on the "
                "train split over seeds are benchmarks/train_split_sweep.py's (docs/results/fair).", "",
                *out["markdown"]]

"""Reproduce the paper's section 4 (docs/model.md section 11): every scenario, figures, tables, report.

    python evaluate.py [--run RUN_DIR] [--run-delay0 RUN_DIR] [--out results/]

Without ``--run`` it uses ``runs/default`` if that holds a trained run (config.json and
checkpoint.msgpack), else trains one with ``train.py``'s defaults first; likewise the gradient-trained
runs (``GRADIENT_RUNS``: the gains and the network trained on the reference plant, the robust delay schedule
on MUSCL at 401 points). Every experiment runs on two plants
(``--plants``): the paper's grid (upwind, the PPO run's points; outputs in ``--out``) and the reference
plant (``TrafficParams.reference``: MUSCL, 801 points, 2 solver steps per 0.1 s; outputs in
``--out``/reference), each controller acting on its own grid (``control.adapter``); ``plants.md`` and
REPORT.md then say, claim by claim, which conclusions survive on the reference plant. Outputs per plant:
metrics.json, robustness.json, claims.json, table2.md, table2.csv, the figures (PNG) and REPORT.md.
Small flags for tests: ``--n-points``, ``--horizon``, ``--seeds``, ``--robust-grid``, ``--reference-grid``.
Table 2's scenario is rerun on each plant refined twice and with the other scheme unless
``--no-numerics-check``.
The same command runs as N cooperating processes with ``--coordinator-address HOST:PORT
--num-processes N --process-id I`` or the ``JAX_*`` variables (``jaxtraffic.platform.distributed``;
docs/tutorials/cluster.md): the batched rollouts (and any training the job starts) are split over
every process's devices, and only process 0 prints and writes.
The logic lives in ``jaxtraffic.paper``; ``main(argv)`` returns the metrics dict.
"""

from __future__ import annotations

import dataclasses
import json
import math
import os
import shutil
import sys
import time
from pathlib import Path
from typing import Any

from jaxtraffic import paper
from jaxtraffic.cli import external, staging
from jaxtraffic.cli import train as train_cli
from jaxtraffic.cli.options import EvaluateOptions, parse_evaluate, program
from jaxtraffic.model.params import TrafficParams
from jaxtraffic.paper.oracle import load_oracle
from jaxtraffic.platform import compile_cache, distributed
from jaxtraffic.runs.config import TrainConfig
from jaxtraffic.runs.config.checks import MAX_STEPS
from jaxtraffic.runs.policy import load_policy, policy_grid

_REF = TrafficParams.reference()
DEFAULT_RUN = Path("runs/default")
PLANTS = ("paper", "reference")
PROG = program("evaluate.py")  # in messages: the program the user typed
MAX_CELLS = 10_000  # of a robustness map (the paper's is 17 x 12 = 204)
MAX_NOISE_SEEDS = 1_000  # of the alpha-noise scenario (the paper: 8)
MAX_HORIZON_S = MAX_STEPS * float(TrafficParams().dt)  # a rollout's step bound (learn.config.checks) at the paper's dt
# wall-clock cap of the PPO training the main job starts when runs/default is missing: a run that has
# not met its stop rule by then keeps its best checkpoint so far (the main job stays bounded)
MAIN_JOB_PPO_WALL_S = 600.0
# the gradient-trained controllers evaluated beside PPO: name -> (run directory under --runs-root, train.py
# flags, training plant). "reference": the reference plant (--reference-grid) with the controller on the paper's
# grid; "half": MUSCL on the paper's grid refined once (401 points, one solver step), the controller on the paper's
# grid: it agrees with the reference plant on which high-alpha plants diverge (MUSCL on the paper's grid does not)
# at a quarter of its cost, so that the robust schedule's CEM (36 plants x 600 s x 24 candidates x 10
# generations) fits its 10-minute budget (docs/model.md section 17, "The training plant's discretisation")
GRADIENT_RUNS = {
    "grad_gains": ("gradient-gains", ["--algo", "gradient", "--policy", "gains"], "reference"),
    "grad_network": ("gradient-network", ["--algo", "gradient", "--policy", "network"], "reference"),
    "grad_robust": ("gradient-robust", ["--algo", "gradient", "--policy", "schedule"], "half"),
}


def parse_args(argv: list[str] | None) -> EvaluateOptions:
    """The options of the command line (``cli.options.EvaluateOptions``; tyro derives the flags from it)."""
    return parse_evaluate(argv, PROG)


def _log(msg: str) -> None:
    if distributed.is_writer():  # process 0 speaks for all
        print(msg, flush=True)


def _curve(path: Path) -> dict | None:
    from jaxtraffic.runs.curve import read_learning_curve

    try:
        return read_learning_curve(path) if path.exists() else None
    except ValueError:
        return None


def find_or_train_run(run: Path | None, n_points: int | None) -> Path:
    """The run to evaluate: ``run``, else runs/default if complete, else a fresh default training."""
    if run is not None:
        if not (run / "config.json").exists():
            raise SystemExit(f"--run {run}: no config.json there")
        return run
    if (DEFAULT_RUN / "config.json").exists() and (DEFAULT_RUN / "checkpoint.msgpack").exists():
        _log(f"using the existing run {DEFAULT_RUN}")
        return DEFAULT_RUN
    _log(f"no trained run at {DEFAULT_RUN}: training one with train.py's defaults first "
         f"(at most {MAIN_JOB_PPO_WALL_S:g} s)")
    targv = ["--out-dir", str(DEFAULT_RUN), "--max-wall-s", str(MAIN_JOB_PPO_WALL_S)] + (
        ["--n-points", str(n_points)] if n_points else [])
    return Path(train_cli.main(targv))


def gradient_controllers(mode: str, root: Path, plant_flags: dict[str, list[str]]
                         ) -> tuple[dict[str, Any], dict[str, Any], dict[str, dict]]:
    """(name -> controller on its own grid, name -> its grid, name -> {"summary", "curve", "run_dir"}) of
    the gradient-trained runs (``GRADIENT_RUNS`` under ``root``), training the missing ones first (with
    ``plant_flags``: per training plant of ``GRADIENT_RUNS``, its flags and the controller grid) when ``mode`` is
    "auto"."""
    ctrls, grids, runs = {}, {}, {}
    for name, (sub, flags, plant) in GRADIENT_RUNS.items() if mode != "none" else ():
        flags = [*flags, *plant_flags[plant]]
        run_dir = root / sub
        if not (run_dir / "summary.json").exists():
            if mode != "auto":
                continue
            resume = ["--resume"] if (run_dir / "checkpoint.msgpack").exists() else []  # an interrupted training
            _log(f"no trained run at {run_dir}: {'continuing' if resume else 'training'} it first "
                 f"(train.py {' '.join(flags + resume)})")
            train_cli.main([*flags, "--out-dir", str(run_dir), *resume])
        ctrl, config = load_policy(run_dir)
        ctrls[name], grids[name] = ctrl, policy_grid(config)
        runs[name] = {"run_dir": str(run_dir), "summary": json.loads((run_dir / "summary.json").read_text()),
                      "curve": _curve(run_dir / "learning_curve.csv")}
    return ctrls, grids, runs


RUN_FILES = ("config.json", "summary.json", "learning_curve.csv")


def export_runs(learned_runs: dict[str, dict], root: Path) -> None:
    """The evaluated controllers themselves, small enough to commit: each run's config.json, summary.json,
    learning curve and the checkpoint ``load_policy`` reads (best.msgpack when there is one, else
    checkpoint.msgpack) in ``root/NAME``, loadable with ``load_policy(root/NAME)``."""
    for name, run in learned_runs.items():
        src, dst = Path(run["run_dir"]), root / name
        if not src.is_dir():  # a --controller of the user's: no run directory
            continue
        dst.mkdir(parents=True, exist_ok=True)
        ckpt = "best.msgpack" if (src / "best.msgpack").exists() else "checkpoint.msgpack"
        for f in (*RUN_FILES, ckpt):
            if (src / f).exists():
                shutil.copyfile(src / f, dst / f)


def parse_grid(text: str, flag: str) -> tuple[int, int]:
    """"AxB" as two ints >= 0 (``SystemExit(2)`` naming ``flag`` otherwise)."""
    try:
        a, b = (int(v) for v in text.lower().split("x"))
    except ValueError:
        raise _fail(f"{flag} must look like AxB (two integers), got {text!r}") from None
    if a < 0 or b < 0:
        raise _fail(f"{flag} sizes must be >= 0, got {text!r}")
    if a * b > MAX_CELLS:
        raise _fail(f"{flag} {text} has {a * b} cells; at most {MAX_CELLS} (each is a 600 s rollout per controller)")
    return a, b


def _describe(run_dir: Path, config: TrainConfig) -> dict[str, Any]:
    return {"run_dir": str(run_dir),
            "description": ("PPO trained" if config.run.algo == "ppo" else f"gradient-trained {config.grad.policy}")
            + f" with D = {config.plant.delay} s, alpha = {config.plant.alpha}",
            "config": dataclasses.asdict(config)}


def _fail(msg: str) -> SystemExit:
    print(f"{PROG}: error: {msg}", file=sys.stderr)
    return SystemExit(2)


def check_args(args: EvaluateOptions) -> tuple[int, int]:
    """Reject bad flags (``SystemExit(2)`` with a message naming the flag, the value and the allowed
    range) before anything is created or compiled; returns the robustness grid sizes."""
    nd, na = parse_grid(args.robust_grid, "--robust-grid")
    try:
        external.parse(args.controller)
    except ValueError as err:
        raise _fail(str(err)) from None
    plants = [p.strip() for p in args.plants.split(",") if p.strip()]
    if not plants or any(p not in PLANTS for p in plants) or len(set(plants)) != len(plants):
        raise _fail(f"--plants must name one or both of {PLANTS}, separated by a comma, got {args.plants!r}")
    args.plants = tuple(p for p in PLANTS if p in plants)
    ref_n, ref_s = parse_grid(args.reference_grid, "--reference-grid")
    if ref_n < 3 or ref_s < 1:
        raise _fail(f"--reference-grid needs >= 3 points and >= 1 substep, got {args.reference_grid!r}")
    parse_grid(args.reference_robust_grid, "--reference-robust-grid")
    if not 1 <= args.noise_seeds <= MAX_NOISE_SEEDS:
        raise _fail(f"--noise-seeds must lie in [1, {MAX_NOISE_SEEDS}], got {args.noise_seeds}")
    for flag, value in (("--horizon", args.horizon), ("--robust-horizon", args.robust_horizon)):
        if value is not None and not (math.isfinite(value) and 0 < value <= MAX_HORIZON_S):
            raise _fail(f"{flag} must be a number of seconds in (0, {MAX_HORIZON_S:.0e}], got {value}")
    if args.n_points is not None and args.n_points < 3:
        raise _fail(f"--n-points must be >= 3, got {args.n_points}")
    for flag, run in (("--run", args.run), ("--run-delay0", args.run_delay0)):
        if run is not None and not (run / "config.json").is_file():
            raise _fail(f"{flag} {run}: not a run directory (no config.json there)")
        if run is not None and not (run / "checkpoint.msgpack").is_file():
            raise _fail(f"{flag} {run}: no checkpoint.msgpack there (the training never completed a chunk)")
    out = args.out
    if out.exists() and not out.is_dir():
        raise _fail(f"--out {out}: exists and is not a directory")
    parent = out
    while not parent.exists():
        parent = parent.parent
    if not parent.is_dir() or not os.access(parent, os.W_OK | os.X_OK):
        raise _fail(f"--out {out}: {parent} is not a writable directory")
    return nd, na


def main(argv: list[str] | None = None) -> dict[str, Any]:
    args = parse_args(argv)
    t0 = time.perf_counter()
    nd, na = check_args(args)
    try:
        distributed.initialize(*args.cluster.values())  # before any computation
    except ValueError as err:
        raise _fail(str(err)) from None
    compile_cache.enable()  # before the first compilation (jaxtraffic.platform.compile_cache)
    final = args.out  # written whole at the end, or left as it was (cli.staging)
    work = staging.staging_dir(final) if distributed.is_writer() else None
    args.out = work or final
    try:
        with staging.signals_raise():
            metrics = _main(args, argv, t0, nd, na)
        if work is not None:
            staging.publish(work, final)
            _log(f"outputs moved into {final}")
        return metrics
    except staging.Stopped as stop:  # SIGINT / SIGTERM / SIGHUP: exit 128 + signal, nothing half-written
        staging.discard(work)
        print(f"{PROG}: interrupted ({stop}): nothing was written to {final} (what it held is unchanged)",
              file=sys.stderr, flush=True)
        raise staging.leave(stop.exit_code) from None
    except (ValueError, FileNotFoundError) as err:  # a broken run directory: one line naming the file
        staging.discard(work)
        print(f"{PROG}: error: {err}", file=sys.stderr, flush=True)
        raise staging.leave(2) from None
    except BaseException:
        staging.discard(work)
        raise


def _main(args: EvaluateOptions, argv: list[str] | None, t0: float, nd: int, na: int) -> dict[str, Any]:
    run_dir = find_or_train_run(args.run, args.n_points)
    ppo, config = load_policy(run_dir)
    for flag, value in (("--horizon", args.horizon), ("--robust-horizon", args.robust_horizon)):
        if value is not None and value < float(config.plant.dt):
            raise ValueError(f"{flag} must be at least one time step ({config.plant.dt} s), got {value}")
    grids = {"ppo": policy_grid(config)}
    n_points, dt = grids["ppo"].n_points, float(config.plant.dt)
    if args.n_points and args.n_points != n_points:
        _log(f"note: --n-points {args.n_points} ignored; the run's controller acts on {n_points} points")
    ppo0, desc0 = None, None
    if args.run_delay0 is not None:
        ppo0, config0 = load_policy(args.run_delay0)
        if policy_grid(config0) != grids["ppo"]:
            raise SystemExit(f"--run-delay0 {args.run_delay0}: its controller's grid differs from --run's "
                             f"({n_points} points, {dt} s)")
        desc0 = _describe(args.run_delay0, config0)
        if float(config0.plant.delay) != 0.0:
            _log(f"WARNING: --run-delay0 {args.run_delay0} was trained with D = {config0.plant.delay} s, not 0")
    policy = _describe(run_dir, config)
    policy0 = desc0 or {**policy, "description": f"the D = 4 s policy ({policy['description']}); "
                        "no D = 0 run was given"}
    ref_n, ref_s = parse_grid(args.reference_grid, "--reference-grid")
    plant_flags = {"reference": ["--n-points", str(ref_n), "--scheme", "muscl", "--substeps", str(ref_s),
                                 "--controller-points", str(n_points)],
                   "half": ["--n-points", str(2 * (n_points - 1) + 1), "--scheme", "muscl", "--controller-points",
                            str(n_points)]}
    grad, grad_grids, grad_runs = gradient_controllers(args.gradient, args.runs_root, plant_flags)
    grids.update(grad_grids)
    own, own_grids = external.load(args.controller)  # --controller: the user's own, judged wherever PPO is
    grids.update(own_grids)
    lc = run_dir / "learning_curve.csv"
    learned_runs = {"ppo": {"run_dir": str(run_dir), "curve": _curve(lc),
                            "summary": json.loads((run_dir / "summary.json").read_text())
                            if (run_dir / "summary.json").exists() else {}}, **grad_runs,
                    **{name: {"run_dir": f"--controller {name}", "summary": {}, "curve": None} for name in own}}
    common = {"dt": dt, "horizon_s": args.horizon, "seeds": tuple(range(args.noise_seeds)),
              "robust_horizon_s": args.robust_horizon or 2.0 * args.horizon,
              "numerics_check": args.numerics_check}
    configs = {"paper": paper.EvalConfig(n_points=n_points, robust_delays=paper.robust_axis(nd, 0.0, 8.0, dt),
                                         robust_alphas=paper.robust_axis(na, 0.05, 0.6), **common)}
    rd, ra = parse_grid(args.reference_robust_grid, "--reference-robust-grid")
    configs["reference"] = paper.EvalConfig(
        n_points=ref_n, scheme="muscl", substeps=ref_s, robust_delays=paper.robust_axis(rd, 0.0, 8.0, dt),
        robust_alphas=paper.robust_axis(ra, 0.05, 0.6), **common)
    meta = {"policy": policy, "policy_delay0": policy0, "argv": list(sys.argv[1:] if argv is None else argv)}
    configs = {plant: configs[plant] for plant in args.plants}
    oracles = {}
    for plant in args.plants:
        oracles[plant] = load_oracle(args.oracle_dir / f"{plant}.json", configs[plant])
        _log(f"   oracle rows of the {plant} map: {args.oracle_dir / (plant + '.json')}" if oracles[plant] else
             f"   no oracle rows for the {plant} map in {args.oracle_dir} (benchmarks/gain_oracle.py --plant {plant})")
    results = paper.evaluate_plants({"ppo": ppo, **grad, **own}, configs, args.out, meta, oracles=oracles, log=_log,
                                    ppo_delay0=ppo0, learning_curve_csv=lc, learned_runs=learned_runs, grids=grids)
    if distributed.is_writer():
        export_runs(learned_runs, args.out / "runs")
    metrics = results[args.plants[0]]
    _log(f"total {time.perf_counter() - t0:.1f} s; verdicts: "
         + "; ".join(f"{k}: {json.dumps(m['meta']['claims'])}" for k, m in results.items()))
    return metrics


if __name__ == "__main__":  # python -m jaxtraffic.cli.evaluate
    main()

"""Reproduce the paper's section 4 (docs/model.md section 11): every scenario, figures, tables, report.

    python evaluate.py [--run RUN_DIR] [--run-delay0 RUN_DIR] [--out results/]

Without ``--run`` it uses ``runs/default`` if that holds a trained run, else trains it first from its recipe
(``paper/recipes/ppo.toml``, ``runs.train_run``); likewise the gradient-trained runs (``GRADIENT_RUNS``: the
registry's learned laws with a recipe, ``paper.laws``). Every experiment runs on two plants (``--plants``): the
paper's grid (outputs in ``--out``) and the reference plant (``TrafficParams.reference``; outputs in
``--out``/reference), each controller acting on its own grid (``control.adapter``); ``plants.md`` and REPORT.md
say, claim by claim, which conclusions survive there. Outputs per plant: metrics.json, robustness.json,
claims.json, table2.md/.csv, the figures and REPORT.md; Table 2's scenario is rerun on each plant refined twice
and with the other scheme unless ``--no-numerics-check``.
The same command runs as N cooperating processes with ``--coordinator-address HOST:PORT
--num-processes N --process-id I`` or the ``JAX_*`` variables (``jaxtraffic.platform.distributed``;
docs/tutorials/cluster.md): the batched rollouts (and any training the job starts) are split over
every process's devices, and only process 0 prints and writes.
``--controller`` policies are imported, made and run for one step on each plant before any training
(``cli.external``); ``--judge`` judges only them against the baselines, training nothing (``cli.judge``).
The logic lives in ``jaxtraffic.paper``; ``main(argv)`` returns the metrics dict.
"""

from __future__ import annotations

import dataclasses
import json
import math
import sys
import time
from pathlib import Path
from typing import Any

import jax

from jaxtraffic import paper
from jaxtraffic.cli import errors, external, judge, staging
from jaxtraffic.cli.options import EvaluateOptions, parse_evaluate, program
from jaxtraffic.io.files import read_json
from jaxtraffic.model.params import TrafficParams
from jaxtraffic.paper import laws
from jaxtraffic.paper.fair import FairStage
from jaxtraffic.paper.oracle import load_oracle
from jaxtraffic.paper.recipes import recipe, training_plant
from jaxtraffic.platform import compile_cache, distributed
from jaxtraffic.runs import train_run
from jaxtraffic.runs.checkpoint import CHECKPOINT, export_policy
from jaxtraffic.runs.config import TrainConfig, load_config
from jaxtraffic.runs.config.checks import MAX_STEPS
from jaxtraffic.runs.policy import load_policy, policy_grid
from jaxtraffic.runs.session import TrainingInterrupted

_REF = TrafficParams.reference()
DEFAULT_RUN = Path("runs/default")
PLANTS = ("paper", "reference")
PROG = program("evaluate.py")  # in messages: the program the user typed
MAX_CELLS = 10_000  # of a robustness map (the paper's is 17 x 12 = 204)
MAX_NOISE_SEEDS = 1_000  # of the alpha-noise scenario (the paper: 8)
MAX_HORIZON_S = MAX_STEPS * float(TrafficParams().dt)  # a rollout's step bound (runs.config.checks) at the paper's dt
GRADIENT_RUNS = laws.recipes()  # the learned laws beside PPO: name -> (its recipe and run folder, training plant)


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
    _log(f"no trained run at {DEFAULT_RUN}: training it first (paper/recipes/ppo.toml, at most "
         f"{recipe('ppo').run.max_wall_s:g} s)")
    config = recipe("ppo").updated(run={"out_dir": str(DEFAULT_RUN)}, plant={"n_points": n_points} if n_points else {})
    trained = train_run(config)
    jax.clear_caches()  # the training's programs are not used again (their memory mappings released)
    return trained


def gradient_controllers(mode: str, root: Path, controller_points: int, reference: tuple[int, int]
                         ) -> tuple[dict[str, Any], dict[str, Any], dict[str, dict]]:
    """(name -> controller on its own grid, name -> its grid, name -> {"summary", "curve", "run_dir"}) of
    the gradient-trained runs (``GRADIENT_RUNS`` under ``root``), training the missing ones first from their recipes
    when ``mode`` is "auto" (the controller on ``controller_points`` nodes, the reference plant ``reference`` =
    (points, substeps)); an interrupted one is resumed."""
    ctrls, grids, runs = {}, {}, {}
    for name, (sub, plant) in GRADIENT_RUNS.items() if mode != "none" else ():
        run_dir = root / sub
        if not (run_dir / "summary.json").exists():
            if mode != "auto":
                continue
            if (run_dir / "checkpoint.msgpack").exists():  # an interrupted training
                config = load_config(run_dir).updated(run={"resume": True})
            else:
                config = recipe(sub).updated(run={"out_dir": str(run_dir)},
                                             **training_plant(plant, controller_points, reference))
            _log(f"no trained run at {run_dir}: {'continuing' if config.run.resume else 'training'} it first "
                 f"(paper/recipes/{sub}.toml on {config.plant.n_points} points)")
            train_run(config)
            jax.clear_caches()  # the training's programs are not used again (their memory mappings released)
        ctrl, config = load_policy(run_dir)
        ctrls[name], grids[name] = ctrl, policy_grid(config)
        runs[name] = {"run_dir": str(run_dir), "summary": read_json(run_dir / "summary.json"),
                      "curve": _curve(run_dir / "learning_curve.csv")}
    return ctrls, grids, runs


RUN_FILES = ("config.json", "config.toml", "summary.json", "learning_curve.csv")


def export_runs(learned_runs: dict[str, dict], root: Path) -> None:
    """The evaluated controllers themselves, small enough to commit: each run's config.json, summary.json,
    learning curve and the checkpoint ``load_policy`` reads (best.msgpack when there is one, else
    checkpoint.msgpack) in ``root/NAME``, loadable with ``load_policy(root/NAME)``. Only regular files are
    copied (a symbolic link in a run directory is skipped, never followed), with their permission bits; a
    gradient-trained run's checkpoint is written without its optimiser state (``export_policy``: it loads, it
    does not resume; a network's is a third of the size)."""
    for name, run in learned_runs.items():
        src, dst = Path(run["run_dir"]), root / name
        if src.is_symlink() or not src.is_dir():  # a --controller of the user's: no run directory
            continue
        dst.mkdir(parents=True, exist_ok=True)
        best = src / "best.msgpack"
        ckpt = "best.msgpack" if best.is_file() and not best.is_symlink() else CHECKPOINT
        for f in (*RUN_FILES, ckpt):
            if f == CHECKPOINT and export_policy(src, dst):
                continue
            if staging.copy_regular(src / f, dst / f) == "link":
                _log(f"note: {src / f} is a symbolic link; not exported")


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


def selected_plants(args: EvaluateOptions) -> tuple[str, ...]:
    """The plants ``--plants`` names, in the order of ``PLANTS``; ``SystemExit(2)`` for a bad value."""
    plants = [p.strip() for p in args.plants.split(",") if p.strip()]
    if not plants or any(p not in PLANTS for p in plants) or len(set(plants)) != len(plants):
        raise _fail(f"--plants must name one or both of {PLANTS}, separated by a comma, got {args.plants!r}")
    return tuple(p for p in PLANTS if p in plants)


def check_args(args: EvaluateOptions) -> tuple[int, int]:
    """Reject bad flags (``SystemExit(2)`` with a message naming the flag, the value and the allowed
    range) before anything is created or compiled; returns the robustness grid sizes."""
    nd, na = parse_grid(args.robust_grid, "--robust-grid")
    try:
        external.parse(args.controller)
    except ValueError as err:
        raise _fail(str(err)) from None
    if args.judge and not args.controller:
        raise _fail("--judge judges your own policy: give it with --controller NAME=SOURCE:FUNCTION[:ARG]")
    selected_plants(args)
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
    try:
        FairStage.from_paths(args.fair, args.tuned, args.split_runs, args.fair_other)
    except ValueError as err:
        raise _fail(str(err)) from None
    for flag, run in (("--run", args.run), ("--run-delay0", args.run_delay0)):
        if run is not None and not (run / "config.json").is_file():
            raise _fail(f"{flag} {run}: not a run directory (no config.json there)")
        if run is not None and not (run / "checkpoint.msgpack").is_file():
            raise _fail(f"{flag} {run}: no checkpoint.msgpack there (the training never completed a chunk)")
    return nd, na


def _raw_out_empty(argv: list[str] | None) -> bool:
    """Whether ``--out ""`` (or ``--out-dir ""``) was given (argparse's ``Path("")`` is ``.``, the current folder)."""
    argv = sys.argv[1:] if argv is None else argv
    flags = ("--out", "--out-dir")
    return any((a in flags and i + 1 < len(argv) and argv[i + 1] == "") or a in [f + "=" for f in flags]
               for i, a in enumerate(argv))


def check_paths(args: EvaluateOptions, argv: list[str] | None) -> None:
    """Every path argument checked before anything is trained (``SystemExit(2)`` naming it)."""
    if _raw_out_empty(argv):
        raise _fail('--out "": an empty path; name a folder (default results/)')
    why = staging.check_out(args.out)
    if why:
        raise _fail(f"--out {args.out}: {why}")
    out = args.out.resolve()
    for flag, path in (("--run", args.run), ("--run-delay0", args.run_delay0), ("--runs-root", args.runs_root)):
        if path is not None and path.resolve().is_relative_to(out):
            raise _fail(f"{flag} {path}: lies inside --out {args.out}, whose entries the report replaces: move the "
                        "run out of it, or choose another --out")
    for spec in external.parse(args.controller):
        source = str(spec["source"])
        if source.endswith(".py") and not Path(source).is_file():
            raise _fail(f"--controller {spec['name']}: no file {source}")
    try:
        norm = external.parse_normalization(args.controller_normalization,
                                            [str(s["name"]) for s in external.parse(args.controller)])
    except ValueError as err:
        raise _fail(str(err)) from None
    for name, path in norm.items():
        if not path.is_file():
            raise _fail(f"--controller-normalization {name}: no file {path}")
    why = external.unnormalised(args.controller, norm)
    if why:
        raise _fail(why)
    for flag, path in (("--runs-root", args.runs_root), ("--oracle-dir", args.oracle_dir)):
        if path.exists() and not path.is_dir():
            raise _fail(f"{flag} {path}: exists and is not a directory")
        if path.is_symlink() and not path.exists():
            raise _fail(f"{flag} {path}: a dangling symbolic link")


def main(argv: list[str] | None = None) -> dict[str, Any]:
    """Run the evaluation (exit statuses: ``cli.errors``; 2 for bad flags, 74 for an OS error, 128+N on a
    signal; ``--out`` is replaced whole or left as it was, ``cli.staging``)."""
    with errors.exit_codes(PROG), errors.interrupt_is_130(PROG):  # `--help | head`, Ctrl-C: one line
        args = parse_args(argv)
        t0 = time.perf_counter()
        nd, na = check_args(args)
        check_paths(args, argv)
    try:
        distributed.initialize(*args.cluster.values())  # before any computation
    except ValueError as err:
        raise _fail(str(err)) from None
    compile_cache.enable()  # before the first compilation (jaxtraffic.platform.compile_cache)
    final = args.out  # written whole at the end, or left as it was (cli.staging)
    stage = None
    try:
        with staging.signals_raise():
            stage = staging.Staging(final) if distributed.is_writer() else None
            args.out = stage.work if stage else final
            metrics = _main(args, argv, t0, nd, na)
            if stage is not None:
                stage.publish()
                _log(f"outputs moved into {final}")
        return metrics
    except TrainingInterrupted as stop:  # a signal during a training the job started: its checkpoint is saved
        if stage is not None:
            stage.discard()
        print(f"{PROG}: interrupted during a training ({stop}): nothing was written to {final}; the run's checkpoint "
              "is kept and the next evaluate.py continues it", file=sys.stderr, flush=True)
        raise staging.leave(stop.exit_code) from None
    except BaseException as err:  # a signal (also through a C extension's error): 128 + signal; else one line
        if stage is not None:
            stage.discard()
        signalled = staging.stopped_in(err)
        if signalled is not None:  # SIGINT / SIGTERM / SIGHUP: exit 128 + signal, nothing half-written
            print(f"{PROG}: interrupted ({signalled}): nothing was written to {final} (what it held is unchanged)",
                  file=sys.stderr, flush=True)
            raise staging.leave(signalled.exit_code) from None
        code = errors.report(PROG, err)
        if code is None:
            raise
        raise staging.leave(code) from None


def _normalization(args: EvaluateOptions) -> dict[str, Path]:
    return external.parse_normalization(args.controller_normalization,
                                        [str(s["name"]) for s in external.parse(args.controller)])


def _judge(args: EvaluateOptions, argv: list[str] | None, t0: float, own: dict[str, Any],
           grids: dict[str, Any]) -> dict[str, Any]:
    """``--judge``: the --controller policies against the baselines on each plant, no training (``cli.judge``);
    each policy is first run for one step on each plant (``external.check_grids``), before the baselines."""
    common: dict[str, Any] = {"dt": float(TrafficParams().dt), "horizon_s": args.horizon,
                              "seeds": tuple(range(args.noise_seeds)), "robust_delays": (), "robust_alphas": (),
                              "numerics_check": False}
    ref_n, ref_s = parse_grid(args.reference_grid, "--reference-grid")
    configs = {"paper": paper.EvalConfig(n_points=args.n_points or paper.EvalConfig.n_points, **common),
               "reference": paper.EvalConfig(n_points=ref_n, scheme="muscl", substeps=ref_s, **common)}
    configs = {p: configs[p] for p in selected_plants(args)}
    meta = {"argv": list(sys.argv[1:] if argv is None else argv)}
    with external.blamed(args.controller):
        external.check_grids(own, grids, configs)
        result = judge.judge_plants(own, grids, configs, args.out, meta, log=_log)
    _log(f"total {time.perf_counter() - t0:.1f} s")
    return result


def planned_config(args: EvaluateOptions) -> TrainConfig:
    """The config of the PPO run the main job will evaluate (``find_or_train_run``), read before it is trained."""
    if args.run is not None:
        return load_config(args.run)
    if (DEFAULT_RUN / "config.json").exists() and (DEFAULT_RUN / "checkpoint.msgpack").exists():
        return load_config(DEFAULT_RUN)
    return recipe("ppo").updated(plant={"n_points": args.n_points} if args.n_points else {})


def plant_configs(args: EvaluateOptions, n_points: int, dt: float, nd: int, na: int) -> dict[str, paper.EvalConfig]:
    """The main job's ``EvalConfig`` of each plant of ``--plants`` (the paper plant on ``n_points``, step ``dt``)."""
    common: dict[str, Any] = {"dt": dt, "horizon_s": args.horizon, "seeds": tuple(range(args.noise_seeds)),
                              "robust_horizon_s": args.robust_horizon or 2.0 * args.horizon,
                              "numerics_check": args.numerics_check}
    configs = {"paper": paper.EvalConfig(n_points=n_points, robust_delays=paper.robust_axis(nd, 0.0, 8.0, dt),
                                         robust_alphas=paper.robust_axis(na, 0.05, 0.6), **common)}
    ref_n, ref_s = parse_grid(args.reference_grid, "--reference-grid")
    rd, ra = parse_grid(args.reference_robust_grid, "--reference-robust-grid")
    configs["reference"] = paper.EvalConfig(
        n_points=ref_n, scheme="muscl", substeps=ref_s, robust_delays=paper.robust_axis(rd, 0.0, 8.0, dt),
        robust_alphas=paper.robust_axis(ra, 0.05, 0.6), **common)
    return {plant: configs[plant] for plant in selected_plants(args)}


def _main(args: EvaluateOptions, argv: list[str] | None, t0: float, nd: int, na: int) -> dict[str, Any]:
    own, own_grids = external.load(args.controller, _normalization(args))  # the user's: checked before training
    if args.judge:
        return _judge(args, argv, t0, own, own_grids)
    if own:
        planned = policy_grid(planned_config(args))
        with external.blamed(args.controller):
            external.check_grids(own, own_grids, plant_configs(args, planned.n_points, planned.dt, nd, na))
    fair_stage = FairStage.from_paths(args.fair, args.tuned, args.split_runs, args.fair_other)  # (checked already)
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
    grad, grad_grids, grad_runs = gradient_controllers(args.gradient, args.runs_root, n_points, (ref_n, ref_s))
    grids.update(grad_grids)
    grids.update(own_grids)
    lc = run_dir / "learning_curve.csv"
    learned_runs = {"ppo": {"run_dir": str(run_dir), "curve": _curve(lc),
                            "summary": read_json(run_dir / "summary.json")
                            if (run_dir / "summary.json").exists() else {}}, **grad_runs,
                    **{name: {"run_dir": f"--controller {name}", "summary": {}, "curve": None} for name in own}}
    meta = {"policy": policy, "policy_delay0": policy0, "argv": list(sys.argv[1:] if argv is None else argv)}
    configs = plant_configs(args, n_points, dt, nd, na)
    plants = tuple(configs)
    oracles = {}
    for plant in plants:
        try:
            oracles[plant] = load_oracle(args.oracle_dir / f"{plant}.json", configs[plant])
        except (TypeError, KeyError, AttributeError, IndexError) as err:  # valid JSON of the wrong shape
            raise ValueError(f"{args.oracle_dir / (plant + '.json')}: not an oracle file "
                             f"(benchmarks/gain_oracle.py): {type(err).__name__}: {err}") from None
        _log(f"   oracle rows of the {plant} map: {args.oracle_dir / (plant + '.json')}" if oracles[plant] else
             f"   no oracle rows for the {plant} map in {args.oracle_dir} (benchmarks/gain_oracle.py --plant {plant})")
    with external.blamed(args.controller):
        results = paper.evaluate_plants({"ppo": ppo, **grad, **own}, configs, args.out, meta, oracles=oracles,
                                        log=_log, ppo_delay0=ppo0, learning_curve_csv=lc, learned_runs=learned_runs,
                                        grids=grids, fair_stage=fair_stage)
    if distributed.is_writer():
        export_runs(learned_runs, args.out / "runs")
    metrics = results[plants[0]]
    _log(f"total {time.perf_counter() - t0:.1f} s; verdicts: "
         + "; ".join(f"{k}: {json.dumps(m['meta']['claims'])}" for k, m in results.items()))
    return metrics


if __name__ == "__main__":  # python -m jaxtraffic.cli.evaluate
    main()

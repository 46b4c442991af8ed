"""A run directory belongs to one run: a fresh run refuses another run's directory unless
``--overwrite`` (which clears it), a lock while training, ``--resume`` keeps the saved run control, and a
training gone NaN stops with a clear error, keeping the last finite checkpoint. Tiny grids."""

from __future__ import annotations

import json

import numpy as np
import pytest
from report_helpers import previous_report
from tiny_runs import TINY

from jaxtraffic.cli import train as train_cli
from jaxtraffic.io.files import clean_stale_tmp
from jaxtraffic.runs import checkpoint as ckpt
from jaxtraffic.runs.config import load_config
from jaxtraffic.runs.session import (
    RUN_FILES,
    RUN_MARKER,
    NonFiniteTraining,
    RunLock,
    check_finite,
    claim_run_dir,
    is_run_dir,
)

GRAD = ["gradient", "--policy", "gains", "--n-points", "21", "--train-delays", "1",
        "--train-horizon-s", "2", "--steps-per-chunk", "1", "--eval-horizon-s", "2", "--quiet"]


def _ours(run):
    run.mkdir()
    claim_run_dir(run, resume=False, overwrite=False, clear=True)  # an empty folder: the marker is written
    assert is_run_dir(run) and [p.name for p in run.iterdir()] == [RUN_MARKER]


def test_a_fresh_run_refuses_another_runs_directory_unless_told_to_clear_it(tmp_path):
    run = tmp_path / "run"
    _ours(run)
    (run / ckpt.CONFIG).write_text("{}")
    (run / "learning_curve.csv").write_text("update\n")
    claim_run_dir(run, resume=False, overwrite=False)  # no results: a run stopped before its first chunk
    for name in (ckpt.CHECKPOINT, ckpt.BEST):
        (run / name).write_text("x")
    (run / "notes.txt").write_text("mine")
    with pytest.raises(ValueError, match=r"holds a run already \(config.json, checkpoint.msgpack, best.msgpack, "
                                         r"learning_curve.csv\); continue it with resume, or set overwrite"):
        claim_run_dir(run, resume=False, overwrite=False)
    claim_run_dir(run, resume=True, overwrite=False)  # resuming is what the directory is for
    claim_run_dir(run, resume=False, overwrite=True)  # allowed, nothing removed yet
    assert (run / ckpt.CHECKPOINT).exists()
    claim_run_dir(run, resume=False, overwrite=True, clear=True)
    assert sorted(p.name for p in run.iterdir()) == [RUN_MARKER, "notes.txt"]  # only the run's own files go


def _snapshot(folder):
    return {p.name: (p.read_bytes(), p.stat().st_mtime_ns) for p in folder.iterdir()}


@pytest.mark.parametrize("names", [("config.toml",), ("config.json",), ("learning_curve.csv", "learning_curve.png"),
                                   (".config.json.abcd1234.tmp", ".notes.tmp"), ("notes.txt",)])
@pytest.mark.parametrize("flags", [(), ("--overwrite",), ("--resume",)])
def test_a_users_folder_is_never_taken_over(tmp_path, capsys, names, flags):
    """A folder holding a user's own files under a run's names (no checkpoint) is refused in one line, exit 2,
    with or without --overwrite, and nothing in it changes (issue 50, item 12)."""
    mine = tmp_path / "p"
    mine.mkdir()
    for name in names:
        (mine / name).write_text(f"the user's {name}\n")
    before = _snapshot(mine)
    code, err = _main(GRAD + ["--out-dir", str(mine), *flags], capsys)
    assert code == 2 and err.count("\n") == 1, err
    assert ("holds no training run of jaxtraffic's" in err) or ("nothing to resume" in err), err
    assert _snapshot(mine) == before
    with pytest.raises(ValueError, match="holds no training run"):
        claim_run_dir(mine, resume=False, overwrite=True, clear=True)
    assert _snapshot(mine) == before and not is_run_dir(mine)


def test_a_marker_must_be_the_real_one_and_only_the_runs_temporaries_are_removed(tmp_path):
    run = tmp_path / "r"
    run.mkdir()
    (run / RUN_MARKER).write_text("mine\n")  # a file of that name with other content proves nothing
    (run / "config.toml").write_text("the user's\n")
    assert not is_run_dir(run)
    with pytest.raises(ValueError, match="holds no training run"):
        claim_run_dir(run, resume=False, overwrite=True, clear=True)
    (run / RUN_MARKER).unlink()
    (run / "config.toml").unlink()
    real = tmp_path / "real-marker"
    _ours(real)
    (run / RUN_MARKER).symlink_to(real / RUN_MARKER)  # nor does a link to a real one
    assert not is_run_dir(run)
    (run / RUN_MARKER).unlink()
    _ours(run / "sub")
    sub = run / "sub"
    for name in (".config.json.abcd1234.tmp", ".best.msgpack.x_y_z_12.tmp", ".notes.txt.abcd1234.tmp", ".a.tmp"):
        (sub / name).write_text("x")
    assert [p.name for p in clean_stale_tmp(sub, (*RUN_FILES, RUN_MARKER))] == [
        ".best.msgpack.x_y_z_12.tmp", ".config.json.abcd1234.tmp"]
    assert sorted(p.name for p in sub.iterdir()) == sorted([RUN_MARKER, ".a.tmp", ".notes.txt.abcd1234.tmp"])


def test_a_run_written_before_the_marker_is_still_ours(tmp_path):
    """Runs of earlier versions (docs/results/runs) have no marker: a checksummed checkpoint proves them ours."""
    run = tmp_path / "old"
    run.mkdir()
    ckpt._write_checked(run / ckpt.BEST, {"x": np.zeros(2)})
    (run / ckpt.CONFIG).write_text("{}")
    assert is_run_dir(run)
    claim_run_dir(run, resume=False, overwrite=True, clear=True)
    assert sorted(p.name for p in run.iterdir()) == [RUN_MARKER]


def test_one_training_at_a_time_holds_the_lock(tmp_path):
    with RunLock(tmp_path):
        with pytest.raises(ValueError, match="another training is writing to it"):
            with RunLock(tmp_path):
                pass
    with RunLock(tmp_path):  # released when the first ended
        pass
    with RunLock(tmp_path, active=False), RunLock(tmp_path):  # a non-writing process takes no lock
        pass


def test_check_finite_names_the_leaves_that_blew_up(tmp_path):
    check_finite("x", {"a": np.ones(3), "b": np.float32(2.0)}, tmp_path, "0 steps")
    with pytest.raises(NonFiniteTraining, match=r"the parameters \['b'\]\['w'\] became NaN/inf; no checkpoint"):
        check_finite("the parameters", {"a": np.ones(3), "b": {"w": np.array([1.0, np.inf])}}, tmp_path, "0 steps")
    (tmp_path / ckpt.CHECKPOINT).write_bytes(b"")
    with pytest.raises(NonFiniteTraining, match=r"the last finite checkpoint \(64 env steps\) is kept"):
        check_finite("the parameters", {"w": np.array(np.nan)}, tmp_path, "64 env steps")


def _main(argv, capsys) -> tuple[int, str]:
    with pytest.raises(SystemExit) as exc:
        train_cli.main(argv)
    return exc.value.code, capsys.readouterr().err


def test_cli_run_directory_ownership_and_resume_keeps_the_saved_run_control(tmp_path, capsys):
    run = tmp_path / "g"
    train_cli.main(GRAD + ["--out-dir", str(run), "--grad-steps", "2"])
    assert json.loads((run / ckpt.SUMMARY).read_text())["updates"] == 2
    # a second fresh run into it: one line, exit 2, before anything is compiled or written
    before = {p.name: p.stat().st_mtime_ns for p in run.iterdir()}
    code, err = _main(GRAD + ["--out-dir", str(run), "--grad-steps", "3"], capsys)
    assert code == 2 and "holds a run already" in err and err.count("\n") == 1
    assert {p.name: p.stat().st_mtime_ns for p in run.iterdir()} == before
    # --resume alone keeps the run's 2 Adam steps (not the default); a changed problem is refused
    train_cli.main(["--resume", "--out-dir", str(run), "--quiet"])
    assert json.loads((run / ckpt.SUMMARY).read_text())["updates"] == 2
    code, err = _main(["--resume", "--out-dir", str(run), "--n-points", "41"], capsys)
    assert code == 2 and "--n-points 41 (the run's value: 21)" in err
    code, err = _main(["ppo", "--resume", "--out-dir", str(run)], capsys)  # (without a subcommand: the run's)
    assert code == 2 and "holds a gradient run: resume it with `train.py gradient --resume`" in err
    # a run-control flag applies, and is recorded
    train_cli.main(["--resume", "--out-dir", str(run), "--grad-steps", "3", "--quiet"])
    assert json.loads((run / ckpt.SUMMARY).read_text())["updates"] == 3 and load_config(run).grad.grad_steps == 3
    # --overwrite clears the old run first
    train_cli.main(GRAD + ["--out-dir", str(run), "--grad-steps", "1", "--overwrite"])
    assert json.loads((run / ckpt.SUMMARY).read_text())["updates"] == 1
    assert len((run / "learning_curve.csv").read_text().splitlines()) == 2  # header + one row: nothing mixed


def test_config_and_checkpoint_are_bound_together(tiny_run_a, tmp_path):
    import shutil

    from jaxtraffic.io.files import write_json
    from jaxtraffic.runs import load_policy
    from jaxtraffic.runs.config import config_json, write_config

    run = tmp_path / "a"
    shutil.copytree(tiny_run_a, run)
    load_policy(run)
    edited = load_config(run).updated(env={"gain_max": 0.123})  # edited after training: another controller
    write_config(edited, run / "config.toml")  # the run's truth: refused against its machine copy
    with pytest.raises(ValueError, match=r"config.toml: \[env\] gain_max = 0.123, but the run's config.json"):
        load_policy(run)
    write_json(run / ckpt.CONFIG, config_json(edited))  # both edited: refused against the checkpoint
    with pytest.raises(ValueError, match=r"gain_max = 0.123, but best.msgpack was trained with .*do not belong"):
        load_policy(run)
    shutil.copy(tiny_run_a / ckpt.CONFIG, run / ckpt.CONFIG)
    write_config(load_config(tiny_run_a).updated(run={"total_steps": 10**9}), run / "config.toml")
    load_policy(run)  # run control is not part of the trained problem
    (run / ckpt.BEST).unlink()  # never silently another policy
    with pytest.raises(ValueError, match=r"best.msgpack is missing, though summary.json says the run kept"):
        load_policy(run)
    load_policy(run, checkpoint="last")


def test_symlinks_in_a_run_directory_are_replaced_not_followed(tmp_path):
    import os

    from jaxtraffic.runs.curve import append_curve, plot_learning_curve, write_curve

    outside = tmp_path / "precious.txt"
    outside.write_text("keep")
    run = tmp_path / "run"
    run.mkdir()
    rows = [{"update": i, "env_steps": 64 * i, "wall_s": 1.0 * i, "mean_reward": -0.6, "eval_reward": -0.5}
            for i in (1, 2)]
    os.symlink(outside, run / "learning_curve.png")
    os.symlink(outside, run / "learning_curve.csv")
    write_curve(run / "learning_curve.csv", rows)
    plot_learning_curve(run / "learning_curve.csv", run / "learning_curve.png")
    assert outside.read_text() == "keep" and not (run / "learning_curve.png").is_symlink()
    os.remove(run / "learning_curve.csv")
    os.symlink(outside, run / "learning_curve.csv")
    with pytest.raises(ValueError, match="cannot append to it"):
        append_curve(run / "learning_curve.csv", rows[0])
    assert outside.read_text() == "keep"


def test_a_compilation_cache_others_can_write_is_not_used(tmp_path, capsys):
    from jaxtraffic.platform import compile_cache

    shared = tmp_path / "cache"
    shared.mkdir()
    shared.chmod(0o777)
    assert not compile_cache.private(shared)
    assert "writable by other users" in capsys.readouterr().err
    shared.chmod(0o700)
    assert compile_cache.private(shared) and capsys.readouterr().err == ""


def test_ppo_gone_nan_stops_with_an_error_and_no_summary(tmp_path, capsys):
    run = tmp_path / "nan"
    code, err = _main([*TINY, "--out-dir", str(run), "--total-steps", "256", "--lr", "1e30", "--val-horizon-s", "0"],
                      capsys)
    assert code == 2 and "training went non-finite" in err and "Traceback" not in err, err
    assert not (run / ckpt.SUMMARY).exists() and not (run / ckpt.BEST).exists()


# --- evaluate.py: outputs whole or not at all, signals (cli.staging) ---------------------------------------------

def test_publish_replaces_what_the_job_wrote_and_leaves_the_rest(tmp_path):
    from jaxtraffic.cli import staging

    out = previous_report(tmp_path / "results", {"REPORT.md": "old", "reference/stale.png": "old"})
    (out / "convergence").mkdir()  # another tool's output in the same directory
    dead = tmp_path / f".results{staging._PARTIAL}killed"  # a killed run's leftovers: our marker, our uid
    dead.mkdir()
    (dead / staging.STAGING_MARKER).write_text("1")
    foreign = tmp_path / f".results{staging._PARTIAL}notours"  # no marker: not ours to remove
    foreign.mkdir()
    stage = staging.Staging(out)
    work = stage.work
    assert work.parent == tmp_path and work.name.startswith(".results.jaxtraffic-partial-")
    assert work.stat().st_mode & 0o777 == 0o700 and not dead.exists() and foreign.is_dir()
    (work / "reference").mkdir(parents=True)
    (work / "REPORT.md").write_text("new")
    (work / "reference" / "metrics.json").write_text("{}")
    stage.publish()
    assert not work.exists() and (out / "REPORT.md").read_text() == "new"
    assert sorted(p.name for p in (out / "reference").iterdir()) == ["metrics.json"]  # whole, not mixed
    assert (out / "convergence").is_dir() and sorted(p.name for p in out.iterdir()) == [
        staging.MARKER, "REPORT.md", "convergence", "reference"]


@pytest.mark.parametrize("outcome", ["done", "signal", "error"])
def test_evaluate_writes_whole_or_nothing(outcome, tmp_path, monkeypatch, capsys):
    import signal

    from jaxtraffic.cli import evaluate as evaluate_cli
    from jaxtraffic.cli import staging

    out = previous_report(tmp_path / "results")

    def fake_main(args, *rest):
        (args.out / "REPORT.md").parent.mkdir(parents=True, exist_ok=True)
        (args.out / "REPORT.md").write_text("new")
        if outcome == "signal":
            raise staging.Stopped(signal.SIGTERM)
        if outcome == "error":
            raise ValueError("runs/x/config.json: broken")
        return {"ok": True}

    monkeypatch.setattr(evaluate_cli, "_main", fake_main)
    argv = ["--out", str(out), "--run", str(tmp_path)]
    (tmp_path / "config.json").write_text("{}")
    (tmp_path / "checkpoint.msgpack").write_bytes(b"")
    if outcome == "done":
        assert evaluate_cli.main(argv) == {"ok": True}
        assert (out / "REPORT.md").read_text() == "new"
    else:
        with pytest.raises(SystemExit) as exc:
            evaluate_cli.main(argv)
        err = capsys.readouterr().err
        assert exc.value.code == (143 if outcome == "signal" else 2) and err.count("\n") == 1, err
        assert ("interrupted (SIGTERM)" if outcome == "signal" else "error: runs/x/config.json: broken") in err
        assert (out / "REPORT.md").read_text() == "earlier"
    assert [p.name for p in tmp_path.iterdir() if ".jaxtraffic-partial-" in p.name] == []


@pytest.mark.parametrize("argv, match", [
    (["--train-delays", "50"], r"train_delays = \[50.0\]: beyond the delay buffer's 10 s"),
    (["--record-every", "1000000"], r"record_every = 1000000: must be <= the training horizon"),
    (["--train-amplitudes", "-1000"], r"\(veh/km\): an initial state leaves the physical region"),
    (["--num-envs", "7", "--tensorboard", "tb"], r"error: --num-envs: a flag of `train.py ppo`, not of"),
    (["--total-steps", "7"], r"--total-steps: a flag of `train.py ppo`, not of `train.py gradient` \(its length"),
])
def test_gradient_scenarios_the_plant_cannot_represent_and_flags_of_the_other_algorithm(argv, match, tmp_path,
                                                                                        capsys):
    code, err = _main([*GRAD, "--out-dir", str(tmp_path / "r"), *argv], capsys)
    assert code == 2 and err.count("\n") == 1, err
    assert __import__("re").search(match, err), err
    assert not (tmp_path / "r").exists()  # nothing half-made


def test_ppo_rules_do_not_block_a_gradient_run_and_gradient_flags_do_not_pass_for_ppo(tmp_path, capsys):
    from jaxtraffic.runs.config import TrainConfig

    TrainConfig.make(run={"algo": "gradient"}, ppo={"num_minibatches": 7})  # PPO's batch rule does not apply
    code, err = _main([*TINY, "--out-dir", str(tmp_path / "p"), "--grad-steps", "3"], capsys)
    assert code == 2 and "--grad-steps: a flag of `train.py gradient`, not of `train.py ppo`" in err
    code, err = _main([*TINY, "--out-dir", str(tmp_path / "p"), "--amp-range", "1000,1000"], capsys)
    assert code == 2 and "amp_range = (1000.0, 1000.0): an initial state of amplitude 1000 veh/km" in err


def test_sizes_and_horizons_beyond_what_can_run_are_flag_errors(tmp_path, capsys):
    from jaxtraffic.runs.config import TrainConfig
    from jaxtraffic.runs.config.checks import check_memory

    for flags, match in ((["--horizon-s", "1e30"], "horizon_s = 1e+30: must be at most 1e+08 time steps"),
                         (["--max-delay-steps", "2147483648"],
                          "max_delay_steps = 2147483648: must lie in [0, 1000000]"),
                         (["--num-envs", "2147483648"], "num_envs = 2147483648: must fit int32"),
                         (["gradient", "--init-gains", "1,2"],
                          "--init-gains: too few values")):
        args = [*TINY, *flags] if flags[0] != "gradient" else [*GRAD, *flags[1:]]
        code, err = _main([*args, "--out-dir", str(tmp_path / "r")], capsys)
        assert code == 2 and match in err and err.count("\n") == 1, err
    with pytest.raises(ValueError, match=r"num_envs = 1024: with num_steps = 100, 4 seed"):
        check_memory(TrainConfig.make(ppo={"num_envs": 1024, "num_steps": 100, "num_seeds": 4}), have=2.0**20)
    check_memory(TrainConfig(), have=2.0**34)  # the defaults fit 16 GiB


def test_the_memory_check_counts_the_delay_buffer_the_suite_and_the_network(tmp_path, capsys):
    """Issue 50, item 15: a delay buffer of 10^6 steps with 4 environments (0.31 GiB estimated before, 16.6 GB
    reached) and a (30000, 30000) network (0.03 MiB estimated before) are refused in one line before anything is
    compiled or written; the estimate grows with each component it counts."""
    from jaxtraffic.runs.config import TrainConfig
    from jaxtraffic.runs.config.checks import check_memory, memory_estimate

    small = TrainConfig.make(ppo={"num_envs": 4, "num_seeds": 1})
    base = memory_estimate(small)
    big_buffer = memory_estimate(small.updated(plant={"max_delay_steps": 10**6}))
    big_net = memory_estimate(small.updated(ppo={"hidden": (30000, 30000)}))
    assert big_buffer["validation suite"] > 5000 * base["validation suite"] and big_buffer["validation suite"] > 2**36
    assert big_net["networks"] > 36 * 4 * 2 * 30000**2 and sum(big_net.values()) > 2**37
    for flags, big in ((["--max-delay-steps", "1000000"], "validation suite"), (["--hidden", "30000", "30000"],
                                                                                 "networks")):
        code, err = _main([*TINY, *flags, "--out-dir", str(tmp_path / "m")], capsys)
        assert code == 2 and err.count("\n") == 1 and f"({big}: " in err, err
        assert not (tmp_path / "m").exists()
    with pytest.raises(ValueError, match=r"the run needs about .* GiB \(validation suite"):
        check_memory(small.updated(plant={"max_delay_steps": 10**6}), have=24 * 2.0**30)


def test_module_entry_points_and_the_gradient_chunk_rule(tmp_path, capsys):
    import jaxtraffic.__main__ as entry

    assert entry.main([]) == 0 and "python -m jaxtraffic {train,evaluate}" in capsys.readouterr().out
    for ask in ("--help", "-h"):  # help is not an error: usage on stdout, exit 0
        assert entry.main([ask]) == 0 and "python -m jaxtraffic {train,evaluate}" in capsys.readouterr().out
    assert entry.main(["bogus"]) == 2 and "unknown command 'bogus'" in capsys.readouterr().err
    code, err = _main([*GRAD, "--grad-steps", "6", "--steps-per-chunk", "5", "--out-dir", str(tmp_path / "r")], capsys)
    assert code == 2 and "grad_steps = 6: must be a multiple of steps_per_chunk (5)" in err
    assert not (tmp_path / "r").exists()

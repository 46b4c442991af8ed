"""Issue 37's hostile cases: what a careless or malicious user can do to ``evaluate.py`` / ``train.py`` and the library,
each asserting the refusal message, the exit status and that nothing outside the job's own output changed (a
checksum of the folder before and after). Destructive cases run in ``tmp_path``; the two-user cases need root
(a folder handed to another uid with ``os.chown``) and are skipped otherwise.

Exit statuses (``jaxtraffic.cli.errors``): 2 bad input, 74 an OS error, 128 + N a signal.
"""

from __future__ import annotations

import dataclasses
import errno
import hashlib
import json
import os
import shutil
import stat
from pathlib import Path

import numpy as np
import pytest
from report_helpers import previous_report

import jaxtraffic as jt
from jaxtraffic.cli import errors, staging
from jaxtraffic.cli import evaluate as evaluate_cli
from jaxtraffic.cli import train as train_cli
from jaxtraffic.control.adaptive import adaptive_backstepping

ROOT_ONLY = pytest.mark.skipif(os.geteuid() != 0, reason="needs a second uid: root can hand a folder to one (chown)")
OTHER_UID = 65534  # nobody


def checksum(folder: Path) -> str:
    """Every entry under ``folder`` (links not followed): its path, type, mode, owner and content or target."""
    h = hashlib.sha256()
    for dirpath, dirnames, filenames in os.walk(folder, followlinks=False):
        for name in sorted(dirnames + filenames):
            p = Path(dirpath) / name
            st = p.lstat()
            h.update(f"{p.relative_to(folder)}|{st.st_mode:o}|{st.st_uid}|".encode())
            if stat.S_ISLNK(st.st_mode):
                h.update(os.readlink(p).encode())
            elif stat.S_ISREG(st.st_mode):
                h.update(p.read_bytes())
        dirnames.sort()
    return h.hexdigest()


def fake_run(where: Path) -> Path:
    """A folder that passes evaluate.py's up-front --run checks (config.json and checkpoint.msgpack exist)."""
    where.mkdir(parents=True, exist_ok=True)
    (where / "config.json").write_text("{}")
    (where / "checkpoint.msgpack").write_bytes(b"")
    return where


def project(root: Path) -> Path:
    """A user's project folder: trained runs, code, a secret."""
    (root / "runs" / "mine").mkdir(parents=True)
    (root / "runs" / "mine" / "checkpoint.msgpack").write_bytes(b"precious")
    (root / "train_notes.md").write_text("weeks of work")
    (root / "secret").write_text("key")
    (root / "secret").chmod(0o600)
    return root


@pytest.fixture
def no_work(monkeypatch):
    """evaluate.py's computation replaced by one that writes a tiny report (``calls`` counts it)."""
    calls = []

    def fake_main(args, *rest):
        calls.append(args.out)
        (args.out / "REPORT.md").write_text("new report")
        (args.out / "runs").mkdir()
        (args.out / "runs" / "x.json").write_text("{}")
        return {"ok": True}

    monkeypatch.setattr(evaluate_cli, "_main", fake_main)
    return calls


def _evaluate(argv: list[str], capsys) -> tuple[int, str]:
    with pytest.raises(SystemExit) as exc:
        evaluate_cli.main(argv)
    err = capsys.readouterr().err
    assert "Traceback" not in err and err.count("\n") == 1, err
    return exc.value.code, err


# ----------------------------------------------------------------------------- 1. --out only where the job owns
def test_out_dot_in_a_project_folder_is_refused(tmp_path, monkeypatch, capsys, no_work):
    """`evaluate.py --out .` in a project folder used to replace (rmtree) the user's ./runs: refused, nothing moved."""
    root = project(tmp_path / "proj")
    run = fake_run(root / "runs" / "mine")
    before = checksum(root)
    monkeypatch.chdir(root)
    code, err = _evaluate(["--run", str(run), "--out", "."], capsys)
    assert code == 2 and "a non-empty folder that holds no report of evaluate.py's" in err
    assert checksum(root) == before and no_work == []


def test_out_empty_string_is_refused(tmp_path, monkeypatch, capsys, no_work):
    root = project(tmp_path / "proj")
    before = checksum(root)
    monkeypatch.chdir(root)
    for argv in (["--out", ""], ["--out="]):
        code, err = _evaluate(["--run", str(fake_run(tmp_path / "r")), *argv], capsys)
        assert code == 2 and "an empty path" in err
    assert checksum(root) == before and no_work == []


def test_out_that_is_a_dangling_symlink_is_refused_before_the_work(tmp_path, capsys, no_work):
    (tmp_path / "res").symlink_to(tmp_path / "gone")
    code, err = _evaluate(["--run", str(fake_run(tmp_path / "r")), "--out", str(tmp_path / "res")], capsys)
    assert code == 2 and "a dangling symbolic link" in err and no_work == []
    assert not (tmp_path / "gone").exists()


def test_empty_folder_new_folder_and_previous_report_are_accepted(tmp_path, no_work):
    run = fake_run(tmp_path / "r")
    (tmp_path / "empty").mkdir()
    for out in (tmp_path / "empty", tmp_path / "new" / "deeper"):
        assert evaluate_cli.main(["--run", str(run), "--out", str(out)]) == {"ok": True}
        assert (out / staging.MARKER).is_file() and (out / "REPORT.md").read_text() == "new report"
    out = tmp_path / "empty"  # now a previous report: replaced, another tool's entry beside it kept
    (out / "convergence").mkdir()
    (out / "convergence" / "c.json").write_text("mine")
    (out / "REPORT.md").write_text("old")
    assert evaluate_cli.main(["--run", str(run), "--out", str(out)]) == {"ok": True}
    assert (out / "REPORT.md").read_text() == "new report" and (out / "convergence" / "c.json").read_text() == "mine"
    assert sorted(p.name for p in tmp_path.iterdir() if p.name.startswith(".")) == [
        ".empty.jaxtraffic-lock", ".new.jaxtraffic-lock"] or all(
        "partial" not in p.name for p in tmp_path.iterdir())


def test_missing_controller_file_is_refused_before_the_work(tmp_path, capsys, no_work):
    code, err = _evaluate(["--run", str(fake_run(tmp_path / "r")), "--out", str(tmp_path / "o"),
                           "--controller", f"mine={tmp_path / 'nope.py'}:make"], capsys)
    assert code == 2 and "--controller mine: no file" in err and no_work == [] and not (tmp_path / "o").exists()


def test_unbounded_seeds_are_refused(tmp_path, capsys, no_work):
    code, err = _evaluate(["--run", str(fake_run(tmp_path / "r")), "--out", str(tmp_path / "o"),
                           "--noise-seeds", "100000000"], capsys)
    assert code == 2 and "--noise-seeds must lie in [1, 1000]" in err and no_work == []


def test_controller_help_says_it_runs_the_users_code(capsys):
    with pytest.raises(SystemExit):
        evaluate_cli.main(["--help"])
    text = " ".join(capsys.readouterr().out.replace("│", " ").split())  # (tyro draws the help in a box)
    assert "RUNS the file's (or module's) code with your permissions" in text


def test_an_entry_placed_during_the_run_in_an_unmarked_folder_is_never_replaced(tmp_path):
    """``check_out`` judged an empty folder fit when the job started; a file of the report's name placed there while
    the job ran (the folder holds no report of ours) is neither replaced nor removed: publishing is refused."""
    out = tmp_path / "res"
    out.mkdir()
    stage = staging.Staging(out)
    (stage.work / "REPORT.md").write_text("new report")
    (out / "REPORT.md").write_text("the user's own notes")
    before = checksum(out)
    with pytest.raises(staging.Refused, match="REPORT.md hold.s. what no report of evaluate.py's wrote there"):
        stage.publish()
    stage.discard()
    assert checksum(out) == before and (out / "REPORT.md").read_text() == "the user's own notes"
    assert (stage.work / "REPORT.md").read_text() == "new report"  # the job's report is kept for the user
    # the same name in a folder holding a report of ours is that report's entry: replaced
    (out / "REPORT.md").unlink()
    previous_report(out)
    stage = staging.Staging(out)
    (stage.work / "REPORT.md").write_text("new report")
    stage.publish()
    assert (out / "REPORT.md").read_text() == "new report"


def test_a_marker_is_not_ownership(tmp_path, no_work):
    """Issue 50, item 13: a copied report (docs/results into a project), an empty or older marker, a symlinked
    marker, a report entry the user added to, a run inside --out: refused, nothing touched."""
    run = fake_run(tmp_path / "r")
    report = previous_report(tmp_path / "report", {"REPORT.md": "ours", "runs/ppo/summary.json": "{}"})
    project_dir = tmp_path / "project"
    shutil.copytree(report, project_dir)  # the report's marker came along with the copy
    (project_dir / "runs" / "mine").mkdir()
    (project_dir / "runs" / "mine" / "config.json").write_text("the user's run")
    empty_marker, linked = tmp_path / "empty-marker", tmp_path / "linked"
    empty_marker.mkdir()
    (empty_marker / staging.MARKER).write_text("")
    (empty_marker / "runs").mkdir()
    linked.mkdir()
    (linked / staging.MARKER).symlink_to(report / staging.MARKER)
    for out, why in ((project_dir, "written for another folder"), (empty_marker, "not one evaluate.py writes"),
                     (linked, "is a symbolic link")):
        before = checksum(out)
        with pytest.raises(SystemExit) as exc:
            evaluate_cli.main(["--run", str(run), "--out", str(out)])
        assert exc.value.code == 2 and checksum(out) == before and no_work == []
        assert why in staging.check_out(out)
    # a genuine report whose runs/ the user added a run to: that entry is not replaced, nor anything else
    (report / "runs" / "mine").mkdir()
    (report / "runs" / "mine" / "config.json").write_text("the user's run")
    before = checksum(report)
    stage = staging.Staging(report)
    (stage.work / "runs").mkdir()
    (stage.work / "REPORT.md").write_text("new")
    with pytest.raises(staging.Refused, match="runs hold"):
        stage.publish()
    stage.discard()
    assert checksum(report) == before
    # evaluating a run that lies inside --out: refused before any work
    inner = fake_run(report / "runs" / "ppo")
    with pytest.raises(SystemExit) as exc:
        evaluate_cli.main(["--run", str(inner), "--out", str(report)])
    assert exc.value.code == 2 and no_work == []


# ----------------------------------------------------------------------------- 2. the staging folder
def test_planted_staging_symlinks_are_never_followed(tmp_path, no_work):
    """Another user's symlinks at every name the staging folder used to take (``.res.partial-PID``) and at the new
    prefix: the job writes into its own mkdtemp folder (0700) and the victim's folder is untouched."""
    victim = project(tmp_path / "victim")
    before = checksum(victim)
    out = tmp_path / "res"
    for pid in range(os.getpid() - 2, os.getpid() + 50):
        (tmp_path / f".res.partial-{pid}").symlink_to(victim)
    (tmp_path / f".res{staging._PARTIAL}planted").symlink_to(victim)
    seen = {}

    def spy(args, *rest):
        seen["work"], seen["mode"] = args.out, args.out.lstat().st_mode
        return no_work_main(args)

    no_work_main = evaluate_cli._main
    evaluate_cli._main = spy
    try:
        assert evaluate_cli.main(["--run", str(fake_run(tmp_path / "r")), "--out", str(out)]) == {"ok": True}
    finally:
        evaluate_cli._main = no_work_main
    assert stat.S_ISDIR(seen["mode"]) and stat.S_IMODE(seen["mode"]) == 0o700
    assert seen["work"].parent == tmp_path and not seen["work"].exists()
    assert checksum(victim) == before and (out / "REPORT.md").read_text() == "new report"
    assert (tmp_path / f".res{staging._PARTIAL}planted").is_symlink()  # not ours: left alone


@ROOT_ONLY
def test_stale_staging_of_another_user_is_not_removed(tmp_path):
    out = tmp_path / "res"
    theirs = tmp_path / f".res{staging._PARTIAL}theirs"
    theirs.mkdir()
    (theirs / staging.STAGING_MARKER).write_text("1")
    (theirs / "data").write_text("theirs")
    os.chown(theirs / staging.STAGING_MARKER, OTHER_UID, -1)
    os.chown(theirs, OTHER_UID, -1)
    mine = tmp_path / f".res{staging._PARTIAL}killed"  # a killed job of ours: removed
    mine.mkdir()
    (mine / staging.STAGING_MARKER).write_text("1")
    before = checksum(theirs)
    stage = staging.Staging(out)
    stage.discard()
    assert theirs.is_dir() and checksum(theirs) == before and not mine.exists()


def test_a_second_job_on_the_same_out_is_refused(tmp_path, capsys, no_work):
    out = tmp_path / "res"
    holder = staging.Staging(out)  # a first job, still writing
    try:
        code, err = _evaluate(["--run", str(fake_run(tmp_path / "r")), "--out", str(out)], capsys)
        assert code == 2 and "another evaluate.py is writing there" in err and no_work == []
    finally:
        holder.discard()
    assert not out.exists()


def test_planted_lock_symlink_is_not_followed(tmp_path, capsys, no_work):
    victim = tmp_path / "victim.txt"
    victim.write_text("do not truncate")
    (tmp_path / ".res.jaxtraffic-lock").symlink_to(victim)
    code, err = _evaluate(["--run", str(fake_run(tmp_path / "r")), "--out", str(tmp_path / "res")], capsys)
    assert code == 74 and "Too many levels of symbolic links" in err and ".res.jaxtraffic-lock" in err
    assert victim.read_text() == "do not truncate" and no_work == []


def test_a_failed_move_leaves_the_previous_report_intact(tmp_path, monkeypatch):
    out = previous_report(tmp_path / "res", {"REPORT.md": "previous", "runs/old.json": "{}"})
    before = checksum(out)
    stage = staging.Staging(out)
    (stage.work / "REPORT.md").write_text("new")
    (stage.work / "runs").mkdir()
    (stage.work / "zzz.png").write_text("new")
    real, calls = os.rename, []

    def flaky(src, dst):
        calls.append(dst)
        if len(calls) == 5:  # mid-way through moving the new entries in (3 old ones moved aside first)
            raise OSError(errno.ENOSPC, "No space left on device", str(dst))
        real(src, dst)

    monkeypatch.setattr(os, "rename", flaky)
    with pytest.raises(OSError):
        stage.publish()
    monkeypatch.setattr(os, "rename", real)
    stage.discard()
    assert checksum(out) == before and not stage.work.exists()
    assert not [p for p in out.iterdir() if p.name.startswith(".jaxtraffic-old-")]


# ----------------------------------------------------------------------------- 3. export_runs and links
def test_export_runs_copies_regular_files_only_and_keeps_restrictive_modes(tmp_path):
    secret = tmp_path / "secret"
    secret.write_text("private key")
    secret.chmod(0o600)
    run = tmp_path / "run"
    run.mkdir()
    (run / "config.json").write_text("{}")
    (run / "config.json").chmod(0o600)
    (run / "summary.json").symlink_to(secret)  # planted
    (run / "checkpoint.msgpack").write_bytes(b"ckpt")
    (run / "best.msgpack").symlink_to(secret)
    out = tmp_path / "out"
    evaluate_cli.export_runs({"ppo": {"run_dir": str(run)}}, out)
    got = sorted(p.name for p in (out / "ppo").iterdir())
    assert got == ["checkpoint.msgpack", "config.json"]
    assert stat.S_IMODE((out / "ppo" / "config.json").stat().st_mode) == 0o600
    assert b"private" not in b"".join(p.read_bytes() for p in (out / "ppo").iterdir())


# ----------------------------------------------------------------------------- 4. the compile cache
def _enable(path: Path, capsys) -> tuple[bool, str]:
    from jaxtraffic.platform import compile_cache

    got = compile_cache.usable(path)  # what enable() checks (this process may have its cache set already)
    return got, capsys.readouterr().err


@ROOT_ONLY
def test_compile_cache_owned_by_another_user_is_refused(tmp_path, capsys):
    cache = tmp_path / "cache"
    cache.mkdir(mode=0o700)
    os.chown(cache, OTHER_UID, -1)
    got, err = _enable(cache, capsys)
    assert not got and "belongs to another user" in err and err.count("\n") == 1


def test_compile_cache_unusable_path_says_so(tmp_path, capsys):
    (tmp_path / "file").write_text("x")
    got, err = _enable(tmp_path / "file" / "cache", capsys)
    assert not got and "cannot be created" in err and err.count("\n") == 1
    (tmp_path / "open").mkdir(mode=0o777)
    (tmp_path / "open").chmod(0o777)
    got, err = _enable(tmp_path / "open", capsys)
    assert not got and "writable by other users" in err


# ----------------------------------------------------------------------------- 5. one line for every OS error
@pytest.mark.parametrize("err, code, text", [
    (OSError(errno.ENOSPC, "No space left on device", "/r/metrics.json"), 74, "/r/metrics.json: No space left"),
    (OSError(errno.EROFS, "Read-only file system", "/r/x.png"), 74, "/r/x.png: Read-only file system"),
    (OSError(errno.ENAMETOOLONG, "File name too long", "/r/" + "n" * 300), 74, "File name too long"),
    (IsADirectoryError(errno.EISDIR, "Is a directory", "/run/best.msgpack"), 74, "/run/best.msgpack: Is a directory"),
    (BrokenPipeError(errno.EPIPE, "Broken pipe"), 74, "standard output was closed"),
    (ValueError("runs/x/config.json: broken"), 2, "runs/x/config.json: broken"),
    (FileNotFoundError(errno.ENOENT, "No such file or directory", "/r/config.json"), 2, "/r/config.json: No such"),
])
def test_evaluate_os_errors_are_one_line_with_their_status(err, code, text, tmp_path, monkeypatch, capsys):
    out = previous_report(tmp_path / "res", {"REPORT.md": "previous"})
    run = fake_run(tmp_path / "r")
    before, parent_before = checksum(out), sorted(p.name for p in tmp_path.iterdir())

    def failing(args, *rest):
        (args.out / "REPORT.md").write_text("half")
        raise err

    monkeypatch.setattr(evaluate_cli, "_main", failing)
    got, msg = _evaluate(["--run", str(run), "--out", str(out)], capsys)
    assert got == code and msg.startswith("evaluate.py: error: ") and text in msg
    assert checksum(out) == before
    assert [n for n in sorted(p.name for p in tmp_path.iterdir()) if n not in parent_before] in (
        [], [".res.jaxtraffic-lock"])  # nothing half-written beside it either


def test_dev_full_through_the_wrapper(capsys):
    with pytest.raises(SystemExit) as exc, errors.exit_codes("train.py"), open("/dev/full", "w") as f:
        f.write("x" * 100_000)
        f.flush()
    assert exc.value.code == 74 and "train.py: error: " in capsys.readouterr().err


def test_train_os_error_is_74(tmp_path, capsys):
    too_long = tmp_path / ("n" * 300)
    with pytest.raises(SystemExit) as exc:
        train_cli.main(["--n-points", "21", "--out-dir", str(too_long / "run"), "--quiet"])
    err = capsys.readouterr().err
    assert exc.value.code == 74 and err.startswith("train.py: error: ") and err.count("\n") == 1, err
    assert err.rstrip().endswith("/run: File name too long") and not list(tmp_path.iterdir())


# ----------------------------------------------------------------------------- 6. library misuse
@pytest.mark.parametrize("call, match", [
    (lambda: jt.stack_params(delay=[]), "the batched fields are empty"),
    (lambda: jt.stack_params(delay=[1.0, 2.0], alpha=[0.1, 0.2, 0.3]), r"different lengths \{'delay': 2, 'alpha': 3\}"),
    (lambda: jt.stack_params(), "give at least one"),
    (lambda: jt.simulate(jt.TrafficParams(n_points=21), n_steps=2**31), r"n_steps must be an int in \[1, 2\*\*31\)"),
    (lambda: jt.simulate(jt.TrafficParams(n_points=21, max_delay_steps=20), jt.backstepping(5.0), n_steps=2),
     r"assumed delay 5 s is 50 steps .* beyond the plant's delay buffer \(max_delay_steps = 20, 2 s\)"),
])
def test_library_misuse_is_refused(call, match):
    with pytest.raises(ValueError, match=match):
        call()


def test_the_gradient_controllers_fixed_road_is_checked():
    from jaxtraffic.learn.gradient import objective

    with pytest.raises(ValueError, match="L = 2000.0 m: the gradient-trained controllers are built for"):
        objective.check_road(jt.TrafficParams(n_points=21, L=2000.0))
    objective.check_road(jt.TrafficParams(n_points=21))


@pytest.mark.parametrize("kwargs, match", [
    ({"seed": 0.0}, "seed must be None"), ({"seed": -1}, "seed must be None"), ({"seed": True}, "seed must be None"),
    ({"checkpoint": "bogus"}, "checkpoint must be 'best' or 'last'"),
])
def test_load_policy_arguments(kwargs, match, tmp_path):
    from jaxtraffic.runs.policy import load_policy

    with pytest.raises(ValueError, match=match):
        load_policy(tmp_path, **kwargs)


def test_load_policy_refuses_a_batched_plant(tmp_path):
    from jaxtraffic.runs.policy import load_policy

    with pytest.raises(ValueError, match="plant must be one concrete TrafficParams"):
        load_policy(tmp_path, plant=jt.stack_params(n_points=21, delay=[0.0, 1.0]))


def test_gym_env_refuses_nan_actions_bad_seeds_and_num_envs():
    pytest.importorskip("gymnasium")
    from jaxtraffic.ecosystem.gym_env import GainEnv, GainVectorEnv

    cfg = {"n_points": 21, "horizon_s": 2.0, "delay": 0.5, "max_delay_steps": 20}
    with pytest.raises(ValueError, match="num_envs must be an int >= 1, got 2.5"):
        GainVectorEnv(num_envs=2.5, **cfg)
    env = GainVectorEnv(num_envs=2, **cfg)
    for seed, match in ((1.5, "seed must be None or an int >= 0, got 1.5"), (-1, "got -1"),
                        ([0, -3], r"seed\[1\] must be None")):
        with pytest.raises(ValueError, match=match):
            env.reset(seed=seed)
    obs, _ = env.reset(seed=0)
    with pytest.raises(ValueError, match="the action must be finite"):
        env.step(np.full((2, 3), np.nan))
    obs2, *_ = env.step(np.full((2, 3), 5.0))  # finite, outside the box: clipped
    assert np.isfinite(obs2).all()
    one = GainEnv(**cfg)
    one.reset(seed=0)
    with pytest.raises(ValueError, match="the action must be finite"):
        one.step(np.array([np.nan, 0.0, 0.0]))
    assert np.isfinite(one.step(np.zeros(3))[0]).all()  # the refused step left the state as it was


def test_gradient_memory_estimate_refuses_before_allocating():
    from jaxtraffic.runs.config import TrainConfig
    from jaxtraffic.runs.gradient.policy import gradient_setup
    from jaxtraffic.runs.gradient.trainer import check_memory, memory_estimate

    grad_config, plant = gradient_setup(TrainConfig.make(
        run={"algo": "gradient"}, grad={"policy": "gains", "train_delays": (1.0,), "train_horizon_s": 2.0},
        plant={"n_points": 21}))
    need = sum(memory_estimate(grad_config, plant).values())
    check_memory(grad_config, plant, have=100 * need)
    with pytest.raises(ValueError, match=r"the run needs about .* GiB \(rollouts: .* GiB\), more than this machine's"):
        check_memory(grad_config, plant, have=need)


# ----------------------------------------------------------------------------- 7. resume on tiny runs
def _copy(src: Path, dst: Path) -> Path:
    shutil.copytree(src, dst)
    return dst


@pytest.mark.slow
def test_resume_with_total_steps_below_the_done_count_is_refused(tiny_runs_root, tmp_path, capsys):
    run = _copy(tiny_runs_root / "A", tmp_path / "A")
    done = json.loads((run / "summary.json").read_text())["env_steps"]
    before = checksum(run)
    with pytest.raises(SystemExit) as exc:
        train_cli.main(["--out-dir", str(run), "--resume", "--total-steps", str(done // 2), "--quiet"])
    err = capsys.readouterr().err
    assert exc.value.code == 2 and f"has already done {done} env steps; --total-steps {done // 2} is below" in err
    assert checksum(run) == before


@pytest.mark.slow
def test_gradient_resume_with_grad_steps_below_the_done_count_is_refused(tiny_runs_root, tmp_path, capsys):
    from jaxtraffic.runs import checkpoint as ckpt

    run = _copy(tiny_runs_root / "runs" / "gradient-gains", tmp_path / "g")
    state, meta = ckpt.load_checkpoint(run)
    ckpt.save_checkpoint(run, state, {**meta, "updates": 4})  # as if 4 Adam steps were done
    before = checksum(run)
    with pytest.raises(SystemExit) as exc:
        train_cli.main(["--out-dir", str(run), "--resume", "--grad-steps", "2", "--quiet"])
    err = capsys.readouterr().err
    assert exc.value.code == 2 and "has already done 4 updates; grad_steps 2 is below that" in err, err
    assert checksum(run) == before


@pytest.mark.slow
def test_edited_best_seed_is_refused(tiny_runs_root, tmp_path):
    from jaxtraffic.runs.policy import load_policy

    run = _copy(tiny_runs_root / "A", tmp_path / "A")
    summary = json.loads((run / "summary.json").read_text())
    if not (run / "best.msgpack").exists():
        pytest.skip("run A kept no best checkpoint")
    summary["best_seed"] = summary["best_seed"] + 1
    (run / "summary.json").write_text(json.dumps(summary))
    with pytest.raises(ValueError, match="best_seed = .* but the scores in .* make member"):
        load_policy(run)


@pytest.mark.slow
def test_gradient_checkpoint_bogus_is_refused(tiny_runs_root):
    from jaxtraffic.runs.policy import load_policy

    with pytest.raises(ValueError, match="checkpoint must be 'best' or 'last', got 'bogus'"):
        load_policy(tiny_runs_root / "runs" / "gradient-gains", checkpoint="bogus")


@pytest.mark.slow
def test_wrong_shape_theta_is_refused_before_resume_rewrites_files(tiny_runs_root, tmp_path, capsys):
    import msgpack

    from jaxtraffic.runs import checkpoint as ckpt

    run = _copy(tiny_runs_root / "runs" / "gradient-gains", tmp_path / "g")
    state, meta = ckpt.load_checkpoint(run)
    state = dict(state)
    state["theta"] = np.zeros(5, np.float32)  # 3 gains expected
    ckpt.save_checkpoint(run, state, meta)
    assert msgpack is not None
    before = checksum(run)
    with pytest.raises(SystemExit) as exc:
        train_cli.main(["--out-dir", str(run), "--resume", "--quiet"])
    err = capsys.readouterr().err
    assert exc.value.code == 2 and "theta has shape (5,)" in err and "Traceback" not in err, err
    assert checksum(run) == before


def test_a_signal_during_the_move_waits_for_it(tmp_path, monkeypatch, capsys):
    """SIGTERM in the middle of publishing: the move completes (the report is whole), then a note says so."""
    import signal

    out = tmp_path / "res"
    stage = staging.Staging(out)
    for name in ("a", "b", "c"):
        (stage.work / name).write_text(name)
    real, calls = os.rename, []

    def rename_and_signal(src, dst):
        calls.append(dst)
        if len(calls) == 2:
            os.kill(os.getpid(), signal.SIGTERM)
        real(src, dst)

    monkeypatch.setattr(os, "rename", rename_and_signal)
    with staging.signals_raise():
        stage.publish()
    assert sorted(p.name for p in out.iterdir()) == [staging.MARKER, "a", "b", "c"]
    assert "SIGTERM received while the report was moved" in capsys.readouterr().err


# ----------------------------------------------------------------------------- round four (issue 50)
def _train(argv: list[str], capsys) -> tuple[int, str]:
    """``train.py argv``: its exit status and stderr, which must be one line and no traceback."""
    with pytest.raises(SystemExit) as exc:
        train_cli.main(argv)
    err = capsys.readouterr().err
    assert "Traceback" not in err and err.count("\n") == 1, err
    return exc.value.code, err


def _numeric_fields() -> list[tuple[str, str, str]]:
    """(section, field, scalar kind) of every int and float field of every config section, walking the dataclasses
    (a tuple field by its element type)."""
    from jaxtraffic.runs.config.tree import SECTIONS, leaf_fields

    out = []
    for s in SECTIONS:
        for f in leaf_fields(s):
            kind = str(f.type).replace(" ", "")
            scalar = "float" if kind.startswith("float") or "tuple[float" in kind else \
                "int" if kind.startswith("int") or "tuple[int" in kind else None
            if scalar is not None:
                out.append((s, f.name, scalar))
    return out


def _shaped(default, x):
    """``x`` in the shape of the field's default (a scalar, a LO,HI pair or a tuple of one)."""
    return x if not isinstance(default, tuple) else (x,) * (len(default) if len(default) in (2, 3) else 1)


NUMERIC = _numeric_fields()


def test_the_walk_finds_every_section_and_both_kinds():
    sections = {s for s, _, _ in NUMERIC}
    assert sections == {"plant", "env", "ppo", "grad", "run"}
    names = {n for _, n, _ in NUMERIC}
    assert {"substeps", "total_steps", "wavenumber_range", "hidden", "lr", "L", "train_wavenumbers"} <= names


@pytest.mark.parametrize("section, name, kind", NUMERIC, ids=[f"{s}.{n}" for s, n, _ in NUMERIC])
def test_every_numeric_field_is_refused_beyond_its_dtype(section, name, kind):
    """Issue 50 item 6: each int field past int32 (the seed past its uint32 range), each float field past
    float32's largest and below its smallest normal magnitude: a one-line ValueError naming the field, never an
    OverflowError from the tracing."""
    from jaxtraffic.runs.config import SECTIONS, TrainConfig
    from jaxtraffic.runs.config.checks import INT32_MAX

    f = next(f for f in dataclasses.fields(SECTIONS[section]) if f.name == name)
    default = f.default
    rule = f.metadata.get("range")
    if kind == "int":
        top = rule[2] if rule is not None and rule[2] is not None and rule[2] > INT32_MAX else INT32_MAX
        bad = [top + 1, 2**63 - 1, -(2**63)]
    else:
        bad = [1e39, -1e39, 1e-39]
    for x in bad:
        with pytest.raises(ValueError, match=rf"^{name} = ") as err:
            TrainConfig.make(**{section: {name: _shaped(default, x)}})
        assert "\n" not in str(err.value)


@pytest.mark.parametrize("table, match", [
    ({"env": {"wavenumber_range": (10**12, 10**12)}}, r"wavenumber_range = 1000000000000: must fit int32"),
    ({"plant": {"substeps": 10**9}}, r"substeps = 1000000000: .* must be at most 1e\+08 solver steps"),
    ({"run": {"total_steps": 2**63 - 1}}, r"total_steps = 9223372036854775807: must fit int32"),
    ({"plant": {"n_points": 21}, "env": {"wavenumber_range": (10**9, 10**9)}}, r"Nyquist limit .* = 10 periods"),
    ({"plant": {"n_points": 21}, "env": {"wavenumber_range": (4, 11)}}, r"Nyquist limit"),
    ({"run": {"algo": "gradient"}, "plant": {"n_points": 21}, "grad": {"train_wavenumbers": (4, 12)}},
     r"train_wavenumbers = \(4, 12\): must be at most the grid's Nyquist limit"),
    ({"run": {"seed": 2**32}}, r"seed = 4294967296: must lie in \[0, 4294967295\]"),
    ({"ppo": {"lr": 1e-40}}, r"lr = 1e-40: must be 0 or at least 1.18e-38"),
])
def test_the_issue_overflows_are_refused(table, match):
    from jaxtraffic.runs.config import TrainConfig

    with pytest.raises(ValueError, match=match):
        TrainConfig.make(**table)


def test_limits_that_are_not_overflows_are_accepted():
    from jaxtraffic.runs.config import TrainConfig

    c = TrainConfig.make(plant={"n_points": 21}, env={"wavenumber_range": (10, 10)}, run={"seed": 2**32 - 1})
    assert c.env.wavenumber_range == (10, 10) and c.run.seed == 2**32 - 1
    assert TrainConfig.make(plant={"substeps": 2}).plant.substeps == 2


def test_overflowing_flags_and_config_values_are_refused_before_any_file(tmp_path, capsys, monkeypatch):
    monkeypatch.chdir(tmp_path)
    out = tmp_path / "r"
    code, err = _train(["--wavenumber-range", "1000000000000", "1000000000000", "--out-dir", str(out)], capsys)
    assert code == 2 and "must fit int32" in err
    code, err = _train(["--n-points", "21", "--wavenumber-range", "1000000000", "1000000000", "--out-dir", str(out)],
                       capsys)
    assert code == 2 and "Nyquist limit" in err
    for text, what in (("[plant]\nsubsteps = 1000000000\n", "solver steps"),
                       ("[run]\ntotal_steps = 9223372036854775807\n", "must fit int32")):
        (tmp_path / "c.toml").write_text(text)
        code, err = _train(["--config", "c.toml", "--out-dir", str(out)], capsys)
        assert code == 2 and what in err and "c.toml: " in err  # the message names the file
    assert sorted(p.name for p in tmp_path.iterdir()) == ["c.toml"]


# item 16: unbounded reads
def _fifo(where: Path) -> Path:
    os.mkfifo(where)
    return where


@pytest.mark.parametrize("make, match", [
    (lambda d: Path("/dev/zero"), "a character device, not a regular file"),
    (lambda d: _fifo(d / "fifo.toml"), "a FIFO (named pipe), not a regular file"),
    (lambda d: (d / "zero.toml").symlink_to("/dev/zero") or d / "zero.toml", "a character device"),
    (lambda d: d, "a directory, not a regular file"),
    (lambda d: (d / "big.toml").write_bytes(b"#" * (2**20 + 1)) and d / "big.toml",
     "1048577 bytes, more than the 1048576 bytes"),
])
def test_config_that_is_no_regular_file_is_refused_without_blocking(make, match, tmp_path, capsys, monkeypatch):
    import signal

    monkeypatch.chdir(tmp_path)
    path = make(tmp_path)
    before = checksum(tmp_path)
    signal.alarm(30)  # a FIFO opened for reading would wait for a writer forever: fail instead
    try:
        code, err = _train(["--config", str(path), "--out-dir", str(tmp_path / "r")], capsys)
    finally:
        signal.alarm(0)
    assert code == 2 and match in err and str(path) in err
    assert checksum(tmp_path) == before


def test_read_regular_limits_and_run_files(tmp_path):
    from jaxtraffic.io import files
    from jaxtraffic.runs import checkpoint
    from jaxtraffic.runs.config import load_config

    (tmp_path / "ok").write_bytes(b"x" * 10)
    assert files.read_regular(tmp_path / "ok", limit=10) == b"x" * 10
    with pytest.raises(ValueError, match="11 bytes, more than the 10"):
        (tmp_path / "ok").write_bytes(b"x" * 11)
        files.read_regular(tmp_path / "ok", limit=10)
    (tmp_path / "link").symlink_to(tmp_path / "ok")
    assert files.read_regular(tmp_path / "link", limit=20) == b"x" * 11
    with pytest.raises(ValueError, match="a symbolic link"):
        files.read_regular(tmp_path / "link", follow=False)
    with pytest.raises(FileNotFoundError):
        files.read_regular(tmp_path / "missing")
    run = tmp_path / "run"
    run.mkdir()
    (run / "config.json").symlink_to("/dev/zero")  # run files that are links to devices
    with pytest.raises(ValueError, match="config.json: a character device"):
        load_config(run)
    _fifo(run / "checkpoint.msgpack")
    with pytest.raises(ValueError, match=r"checkpoint.msgpack: a FIFO"):
        checkpoint.load_checkpoint(run)


# item 17: config files that do what flags may not
def _saved_run(where: Path, **tables) -> Path:
    """A run directory holding only the config.json a fresh run would write (enough for the resume's checks)."""
    from jaxtraffic.io.files import write_json
    from jaxtraffic.runs.config import TrainConfig, config_json

    where.mkdir(parents=True)
    config = TrainConfig.make(plant={"n_points": 21}, run={"out_dir": str(where)}, **tables)
    write_json(where / "config.json", config_json(config))
    (where / "checkpoint.msgpack").write_bytes(b"precious")
    return where


@pytest.mark.parametrize("key", ["overwrite", "resume"])
def test_run_actions_in_a_config_file_are_refused(key, tmp_path, capsys, monkeypatch):
    monkeypatch.chdir(tmp_path)
    run = _saved_run(tmp_path / "r")
    (tmp_path / "c.toml").write_text(f"[run]\n{key} = true\n")
    before = checksum(tmp_path)
    code, err = _train(["--config", "c.toml", "--out-dir", str(run)], capsys)
    assert code == 2 and f"c.toml: [run] {key} is an action on the run directory" in err and f"--{key}" in err
    assert checksum(tmp_path) == before


def test_config_with_resume_honours_run_control_and_refuses_the_rest(tmp_path):
    run = _saved_run(tmp_path / "r")
    (tmp_path / "lr.toml").write_text("[ppo]\nlr = 0.5\n")
    (tmp_path / "tau.toml").write_text("[plant]\ntau_acc = 2.5\n")  # a field without a flag
    (tmp_path / "steps.toml").write_text("[run]\ntotal_steps = 1234\nquiet = true\n")
    for name, match in (("lr.toml", r"these settings would change it: lr in .*lr.toml = 0.5 \(the run's value: "
                                    r"0.001\)"), ("tau.toml", r"tau_acc in .*tau.toml = 2.5")):
        config, _, given = train_cli.parse(["--resume", "--out-dir", str(run), "--config", str(tmp_path / name)])
        with pytest.raises(ValueError, match=match):
            train_cli.resumed_config(config, given)
    config, _, given = train_cli.parse(["--resume", "--out-dir", str(run), "--config", str(tmp_path / "steps.toml"),
                                        "--no-quiet"])
    resumed = train_cli.resumed_config(config, given)
    assert resumed.run.total_steps == 1234 and resumed.run.quiet is False and resumed.run.resume
    assert resumed.ppo.lr == 1e-3 and resumed.plant.n_points == 21  # the run's own


def test_boolean_flags_work_both_ways_when_the_file_sets_them(tmp_path):
    (tmp_path / "q.toml").write_text("[run]\nquiet = true\nrequire_certificate = false\n")
    q = str(tmp_path / "q.toml")
    assert train_cli.config_from_args(["--config", q, "--quiet"]).run.quiet is True
    assert train_cli.config_from_args(["--config", q, "--no-quiet"]).run.quiet is False
    assert train_cli.config_from_args(["--config", q]).run.quiet is True
    assert train_cli.config_from_args(["--config", q, "--require-certificate"]).run.require_certificate is True
    assert train_cli.config_from_args(["--quiet"]).run.quiet is True  # without a file: as before
    with pytest.raises(ValueError, match="unrecognized arguments: --no-quiet"):
        train_cli.config_from_args(["--no-quiet"])


@pytest.mark.parametrize("version", [99, None, "four", True, 2])
def test_config_json_version_is_checked(version, tmp_path, capsys):
    from jaxtraffic.io.files import read_json, write_json

    run = _saved_run(tmp_path / "r")
    data = read_json(run / "config.json")
    write_json(run / "config.json", {**data, "version": version})
    before = checksum(tmp_path)
    code, err = _train(["--resume", "--out-dir", str(run)], capsys)
    from jaxtraffic.runs.config.tree import CONFIG_VERSION

    assert code == 2 and f"config.json: config version {version!r}; this jaxtraffic reads versions 3 to " \
        f"{CONFIG_VERSION}" in err
    assert checksum(tmp_path) == before


# item 19: the smaller list
def test_hidden_zero_is_refused_before_any_file(tmp_path, capsys, monkeypatch):
    monkeypatch.chdir(tmp_path)
    (tmp_path / "h.toml").write_text("[ppo]\nhidden = [0]\n")
    code, err = _train(["--config", "h.toml", "--out-dir", "r"], capsys)
    assert code == 2 and "h.toml: hidden = 0: must be >= 1" in err
    code, err = _train(["--hidden", "64", "0", "--out-dir", "r"], capsys)
    assert code == 2 and "hidden = 0: must be >= 1" in err
    assert [p.name for p in tmp_path.iterdir()] == ["h.toml"]


@pytest.mark.parametrize("kwargs, match", [
    ({"alpha0": 5.0}, r"alpha0 must lie in \[0, 1\], got \[5.0\]"),
    ({"alpha0": -0.1}, r"alpha0 must lie in \[0, 1\]"),
    ({"forgetting": 0.0}, r"forgetting must lie in \(0, 1\]"),
    ({"forgetting": 1.5}, r"forgetting must lie in \(0, 1\]"),
    ({"min_info": 0.0}, r"min_info must lie in \(0, inf\) \(m/s\)\^2"),
    ({"shock_scale": 0.0}, r"shock_scale must lie in \(0, inf\) veh/m"),
    ({"delay": 1e9}, r"assumed delay must lie in \[0, 3600\] s, got 1000000000.0"),
    ({"delay": -1.0}, r"assumed delay must lie in \[0, 3600\] s"),
    ({"forgetting": float("nan")}, "forgetting must be finite"),
])
def test_adaptive_backstepping_refuses_settings_out_of_range(kwargs, match):
    with pytest.raises(ValueError, match=match):
        adaptive_backstepping(**kwargs)


def test_adaptive_backstepping_accepts_its_range_and_traced_settings():
    import jax

    assert adaptive_backstepping(4.0, alpha0=1.0, forgetting=1.0, min_info=1e-9).name == "adaptive_backstepping"
    assert adaptive_backstepping().settings.alpha0 != adaptive_backstepping().settings.alpha0  # NaN default
    jax.jit(lambda d: adaptive_backstepping(d).settings.delay)(1e9)  # traced: not checked (no jnp ops there)


def test_ctrl_c_while_parsing_is_one_line_and_130(capsys, monkeypatch):
    def interrupted(argv=None):
        raise KeyboardInterrupt

    monkeypatch.setattr(train_cli, "parse", interrupted)
    code, err = _train([], capsys)
    assert code == 130 and "interrupted (Ctrl-C) before the job started" in err
    monkeypatch.setattr(evaluate_cli, "parse_args", interrupted)
    code, err = _evaluate([], capsys)
    assert code == 130 and err.startswith("evaluate.py: error: interrupted")


@pytest.mark.parametrize("kw, match", [({"lr": 0.1}, r"'lr' is a setting of the training \(\[ppo\]\)"),
                                       ({"out_dir": "x"}, r"'out_dir' is a setting of the training \(\[run\]\)"),
                                       ({"total_steps": 5}, "not of the environment")])
def test_environment_refuses_training_keywords(kw, match):
    from jaxtraffic.ecosystem import resolve_env_params

    with pytest.raises(TypeError, match=match):
        resolve_env_params(n_points=21, **kw)
    assert resolve_env_params(n_points=21, horizon_s=2.0).traffic.n_points == 21


def test_gym_env_refuses_complex_and_non_numeric_actions():
    pytest.importorskip("gymnasium")
    from jaxtraffic.ecosystem.gym_env import GainEnv

    env = GainEnv(n_points=21, horizon_s=2.0, delay=0.5, max_delay_steps=20)
    env.reset(seed=0)
    for action in (np.array([1j, 0.0, 0.0]), np.array([True, False, True]), np.array(["a", "b", "c"])):
        with pytest.raises(ValueError, match="the action must be real numbers"):
            env.step(action)
    assert np.isfinite(env.step(np.zeros(3))[0]).all()


def test_library_misuse_messages_say_what_is_expected():
    import jax
    import jax.numpy as jnp

    p = jt.TrafficParams(n_points=21)
    with pytest.raises(ValueError, match="batch_controller=True needs a controller whose settings carry a leading "
                                         "batch axis"):
        jt.simulate_batch(p, jt.backstepping(1.0), n_steps=3, batch_controller=True)
    with pytest.raises(ValueError, match="batch_controller=True needs a controller"):
        jt.simulate_batch(p, None, n_steps=3, batch_controller=True)
    for bad in ("backstepping", jt.backstepping, 3.0):
        with pytest.raises(TypeError, match=r"controller must be a jaxtraffic Controller .* got "):
            jt.simulate(p, bad, n_steps=3)
    res = jt.simulate_batch(p, jax.vmap(jt.backstepping)(jnp.array([1.0, 2.0])), n_steps=3, batch_controller=True)
    assert res.metrics["diverged_reason"].shape == (2,)


def test_a_recipe_error_names_the_recipe(monkeypatch):
    from jaxtraffic.paper import recipes

    real = recipes.tables_of_toml
    monkeypatch.setattr(recipes, "tables_of_toml", lambda data, where: {**real(data, where), "ppo": {"lr": -1.0}})
    with pytest.raises(ValueError, match=r"^jaxtraffic/paper/recipes/ppo.toml: lr = -1.0: must be > 0"):
        recipes.recipe("ppo")


@pytest.mark.parametrize("junk", [{"env_steps": -5}, {"env_steps": 2**62}, {"env_steps": True},
                                  {"env_steps": 64, "wall_s": "soon"}, {"env_steps": 64, "updates": 1.5},
                                  {"env_steps": 64, "stopped": "no"}, {"env_steps": 64, "rows": [1, 2]},
                                  {"env_steps": 64, "seconds_to_stop_rule": -1.0},
                                  {"env_steps": 64, "config_problem": "{not json"}])
def test_a_checkpoint_with_a_valid_checksum_and_junk_progress_is_refused(junk, tmp_path, capsys):
    """A crafted checkpoint (written by save_checkpoint: the checksum is right) whose progress is junk: one line,
    status 2, before anything in the run directory is rewritten."""
    from jaxtraffic.runs import checkpoint

    run = _saved_run(tmp_path / "r")
    checkpoint.save_checkpoint(run, {"update": np.zeros(1)}, junk)
    with pytest.raises(ValueError, match="its progress is not what a run writes"):
        checkpoint.load_checkpoint(run)
    before = checksum(tmp_path)
    code, err = _train(["--resume", "--out-dir", str(run)], capsys)
    assert code == 2 and "checkpoint.msgpack: its progress is not what a run writes" in err
    assert checksum(tmp_path) == before
    checkpoint.save_checkpoint(run, {"update": np.zeros(1)}, {"env_steps": 64, "seconds_to_stop_rule": None})
    assert checkpoint.load_checkpoint(run)[1]["env_steps"] == 64  # what a run writes is accepted


def test_a_signal_that_reaches_evaluate_through_a_c_extensions_error_is_still_a_signal(tmp_path, monkeypatch, capsys):
    """A signal handled while a C extension runs Python code of its own arrives as that extension's SystemError
    ("returned a result with an exception set"), the ``Stopped`` its cause: still 128 + signal, one line, the
    previous report untouched (seen in CI: SIGINT inside NumPy's call of ml_dtypes' ``__numpy_dtype__``)."""
    import signal

    from jaxtraffic.cli import staging

    out = previous_report(tmp_path / "res", {"REPORT.md": "previous"})
    run = fake_run(tmp_path / "r")
    before = checksum(out)

    def interrupted(args, *rest):
        (args.out / "REPORT.md").write_text("half")
        try:
            raise staging.Stopped(signal.SIGINT)
        except staging.Stopped as stop:
            raise SystemError("<function f> returned a result with an exception set") from stop

    monkeypatch.setattr(evaluate_cli, "_main", interrupted)
    got, msg = _evaluate(["--run", str(run), "--out", str(out)], capsys)
    assert got == 128 + signal.SIGINT and msg.startswith("evaluate.py: interrupted (SIGINT): nothing was written")
    assert checksum(out) == before
    assert staging.stopped_in(ValueError("x")) is None

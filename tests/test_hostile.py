"""Issue 37's hostile cases: what a careless or malicious user can do to ``evaluate.py`` / ``train.py`` and the library,
each asserting the refusal message, the exit status and that nothing outside the job's own output changed (a
checksum of the folder before and after). Destructive cases run in ``tmp_path``; the two-user cases need root
(a folder handed to another uid with ``os.chown``) and are skipped otherwise.

Exit statuses (``jaxtraffic.cli.errors``): 2 bad input, 74 an OS error, 128 + N a signal.
"""

from __future__ import annotations

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

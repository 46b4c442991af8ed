"""The command line explains itself (issue 50, items 3, 4, 5, 9): ``--version`` and ``--help | head`` on both
programs, the program's name under ``python -m jaxtraffic``, evaluate.py's ``--out-dir``, ``train.py --recipe``,
the PPO run's closing lines (the stop rule's conditions, the best checkpoint's score, the rounding of
``--total-steps``) and the main job's time given alike in every document."""

from __future__ import annotations

import re
import subprocess
import sys
import tomllib
from importlib import import_module
from pathlib import Path

import numpy as np
import pytest
from tiny_runs import xla_env

import jaxtraffic
from jaxtraffic.cli import evaluate as evaluate_cli
from jaxtraffic.cli import options
from jaxtraffic.cli import train as train_cli
from jaxtraffic.paper import recipes
from jaxtraffic.paper.recipes import NAMES, recipe
from jaxtraffic.runs.config import RunConfig
from jaxtraffic.runs.ppo import selection
from jaxtraffic.runs.session import rounding_note

REPO = Path(__file__).resolve().parents[1]


def _env() -> dict:
    return xla_env(PYTHONPATH=str(REPO))


# ----------------------------------------------------------------------------- item 4: --version, --help | head
@pytest.mark.parametrize("script", ["train.py", "evaluate.py"])
def test_help_into_a_closed_pipe_is_one_line_not_a_traceback(script):
    """``PROG --help | head``: the reader has gone before the help is written (the pipe's read end is closed at
    once; the program is still importing jax): one line, exit 74, no traceback, for both programs alike."""
    proc = subprocess.Popen([sys.executable, str(REPO / script), "--help"], cwd=REPO, env=_env(),
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    proc.stdout.close()
    err = proc.stderr.read()
    rc = proc.wait(timeout=120)
    assert rc == 74 and "Traceback" not in err and "Exception ignored" not in err, (rc, err[-2000:])
    assert err.strip() == f"{script}: error: standard output was closed (broken pipe); stopped"


def test_evaluate_version(capsys):
    with pytest.raises(SystemExit) as exc:
        evaluate_cli.main(["--version"])
    assert exc.value.code == 0 and capsys.readouterr().out.split() == [evaluate_cli.PROG, jaxtraffic.__version__]
    with pytest.raises(SystemExit) as exc:  # anywhere on the line, as train.py's
        evaluate_cli.main(["--plants", "paper", "--version"])
    assert exc.value.code == 0 and capsys.readouterr().out.startswith("evaluate.py ")


def test_the_program_name_is_what_the_user_typed(monkeypatch):
    cases = {str(REPO / "jaxtraffic" / "__main__.py"): ("python -m jaxtraffic train", "python -m jaxtraffic evaluate"),
             "/venv/bin/jaxtraffic-train": ("jaxtraffic-train", "jaxtraffic-train"),
             str(REPO / "evaluate.py"): ("evaluate.py", "evaluate.py"), "-c": ("train.py", "evaluate.py")}
    for argv0, (train_name, evaluate_name) in cases.items():
        monkeypatch.setattr(sys, "argv", [argv0])
        assert (options.program("train.py"), options.program("evaluate.py")) == (train_name, evaluate_name), argv0


def test_python_m_jaxtraffic_train_help_shows_its_own_usage():
    out = subprocess.run([sys.executable, "-m", "jaxtraffic", "train", "--help"], cwd=REPO, env=_env(),
                         capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr[-2000:]
    assert out.stdout.startswith("usage: python -m jaxtraffic train ") and "train.py" not in out.stdout


def test_evaluate_takes_out_dir_as_train_does(capsys):
    assert evaluate_cli.parse_args(["--out-dir", "r1"]).out == Path("r1")
    assert evaluate_cli.parse_args(["--out-dir=r2"]).out == Path("r2")
    assert evaluate_cli.parse_args(["--out", "r3"]).out == Path("r3")
    for argv in (["--out-dir", ""], ["--out-dir="]):  # the empty path is the current folder: refused alike
        with pytest.raises(SystemExit) as exc:
            evaluate_cli.main(argv)
        assert exc.value.code == 2 and 'an empty path' in capsys.readouterr().err


# ----------------------------------------------------------------------------- item 9: the recipes by name
def test_console_scripts_exist():
    scripts = tomllib.loads((REPO / "pyproject.toml").read_text())["project"]["scripts"]
    assert set(scripts) == {"jaxtraffic-train", "jaxtraffic-evaluate"}
    for target in scripts.values():
        module, func = target.split(":")
        assert callable(getattr(import_module(module), func))


@pytest.mark.parametrize("name", NAMES)
def test_recipe_by_name_is_the_recipe_and_flags_override_it(name):
    assert train_cli.config_from_args(["--recipe", name]) == recipe(name)
    algo = recipe(name).run.algo  # the subcommand follows the recipe, or is given
    assert train_cli.config_from_args([algo, f"--recipe={name}", "--seed", "7"]) == recipe(name).updated(
        run={"seed": 7})


def test_an_unknown_recipe_and_recipe_with_config_are_one_line_errors(capsys, tmp_path):
    with pytest.raises(SystemExit) as exc:
        train_cli.main(["--recipe", "ppo2"])
    err = capsys.readouterr().err
    assert exc.value.code == 2 and err.count("\n") == 1 and "--recipe 'ppo2': no such recipe" in err
    assert all(n in err for n in NAMES)
    config = tmp_path / "c.toml"
    config.write_text("[run]\nseed = 1\n")
    with pytest.raises(SystemExit) as exc:
        train_cli.main(["--recipe", "ppo", "--config", str(config), "--out-dir", str(tmp_path / "run")])
    err = capsys.readouterr().err
    assert exc.value.code == 2 and err.count("\n") == 1 and "give one" in err
    assert not (tmp_path / "run").exists()


def test_every_recipe_is_run_by_the_main_job_as_its_docstring_says():
    assert {"ppo", *(sub for sub, _ in evaluate_cli.GRADIENT_RUNS.values())} == set(NAMES)
    assert "not yet" not in (recipes.__doc__ or "") and all(f"{n}.toml" in recipes.__doc__ for n in NAMES)


# ----------------------------------------------------------------------------- item 5: the closing lines
def _ev(reward, wave, diverged=(False, False)):
    return {"final_reward": np.asarray(reward, np.float32), "wave_speed": np.asarray(wave, np.float32),
            "diverged": np.asarray(diverged)}


def test_the_stop_rule_says_which_condition_failed_with_the_values():
    run = RunConfig()  # reward >= -0.1, wave speed >= 0.5 m/s, certificate, validation <= 1
    text = selection.rule_text(run, _ev([-0.05, -0.3], [0.31, 0.8]), None, None)
    member0, member1 = text.split("; member 1: ")
    assert member0.startswith("member 0: reward target met (eval reward -0.05 >= -0.1, dimensionless)")
    assert "wave speed not met (+0.31 m/s < 0.5 m/s)" in member0 and "certificate not checked" in member0
    assert "validation not run" in member0
    assert member1.startswith("reward target not met (eval reward -0.3 < -0.1") and "wave speed met (+0.80" in member1
    # both cheap conditions met: the certificate and the validation score, with the target
    score = np.array([0.84, 1.7])
    text = selection.rule_text(run, _ev([-0.05, -0.02], [0.9, 0.8]), np.array([True, True]), score)
    assert "certificate met, validation met (score 0.84 <= 1)" in text
    assert "validation not met (score 1.7 > 1)" in text
    text = selection.rule_text(run, _ev([-0.05, -0.02], [0.9, 0.8]), np.array([False, True]),
                               np.array([selection.UNVALIDATED, selection.BAD]))
    assert "member 0: " in text and "certificate not met, validation not run" in text
    assert "validation not met (rejected: a rollout diverged" in text
    assert "reward target not met (the evaluation diverged)" in selection.rule_text(
        run, _ev([np.nan, -0.02], [0.9, 0.8], (True, False)), None, None)
    paper_only = RunConfig(min_wave_speed=None, require_certificate=False, val_horizon_s=0.0)
    assert selection.rule_text(paper_only, _ev([-0.5], [-3.0], (False,)), None, None) == (
        "member 0: reward target not met (eval reward -0.5 < -0.1, dimensionless)")


def test_the_best_checkpoint_is_said_with_its_unit_never_the_placeholder():
    kept = selection.scores(np.array([-0.5, -0.7], np.float32), np.array([False, False]), None, None)
    for measure in ("the suite's measure", None):
        text = selection.best_text(float(kept[0]), 0, 64, measure)
        assert "1e+07" not in text and text.startswith("no scored checkpoint") and "member 0 at 64 env steps" in text
    text = selection.best_text(selection.BAD, 1, 128, "the worst ratio")
    assert "1e+06" not in text and "rejected" in text
    text = selection.best_text(0.84, 1, 128, "the worst ratio to backstepping")
    assert text.startswith("best checkpoint: member 1 at 128 env steps, validation score 0.84 (")
    assert "dimensionless" in text and "backstepping" in text
    no_suite = selection.scores(np.array([-0.05], np.float32), np.array([True]), None, None)
    assert "evaluation reward -0.05 (dimensionless)" in selection.best_text(float(no_suite[0]), 0, 64, None)
    assert selection.best_text(np.inf, 0, 0, "the worst ratio") == "no best checkpoint kept"


def test_rounding_of_total_steps_is_said_with_its_reason():
    ppo = recipe("ppo").ppo  # the numbers: 400 000 requested, 422 400 run
    per_chunk = ppo.steps_per_update * ppo.updates_per_chunk
    note = rounding_note(400_000, per_chunk, "--total-steps", "env steps", "128 envs x 100 steps x 3 updates")
    assert note.startswith("note: --total-steps 400000 is rounded up to 422400 env steps")
    assert f"whole chunks of {per_chunk} env steps (128 envs x 100 steps x 3 updates)" in note
    assert rounding_note(11 * per_chunk, per_chunk, "--total-steps", "env steps", "x") == ""


# ----------------------------------------------------------------------------- item 3: numbers that agree
TIME = re.compile(r"about (\d+) minutes the first time, (\d+|less) once the compilation cache is warm")
MAIN_JOB_TIME_IN = ("README.md", "docs/index.md", "docs/tutorials/own-policy.md", "docs/main-job.md")


def test_the_main_job_time_is_the_readme_s_everywhere():
    found = {}
    for name in MAIN_JOB_TIME_IN:
        text = " ".join((REPO / name).read_text().split())  # line breaks as spaces
        found[name] = TIME.findall(text)
        assert found[name], f"{name} does not give the main job's time as the README does"
        assert not re.search(r"main job[^.]*about \d+ minutes\)", text), name  # no other figure beside it
    assert len({t for times in found.values() for t in times}) == 1, found


def test_the_cluster_tutorial_says_import_jaxtraffic_splits_nothing():
    text = " ".join((REPO / "docs/tutorials/cluster.md").read_text().split())
    assert "`import jaxtraffic` itself changes nothing" in text
    assert "`import jaxtraffic` gives" not in text

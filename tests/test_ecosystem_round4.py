"""Issue 50, round four of the ecosystem: ``gymnax.make("jaxtraffic/Gain-v0")`` in either import order (an
import hook registers the id when gymnax is imported after jaxtraffic), checked in fresh interpreters with a
stand-in gymnax package (always) and with the real one (when the ``[gymnax]`` extra is installed)."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest
from extras import available

REPO = Path(__file__).resolve().parents[1]

# a stand-in for gymnax >= 1.0's registry (register / registered_envs / make), as small as the real API
FAKE_GYMNAX = '''
_registry = {}
registered_envs = []
def register(env_id, factory):
    if env_id in _registry:
        raise ValueError(f"{env_id} is already registered")
    _registry[env_id] = factory
    registered_envs.append(env_id)
def make(env_id, **kwargs):
    return _registry[env_id], kwargs
'''

ORDERS = {"gymnax first": "import gymnax, jaxtraffic", "jaxtraffic first": "import jaxtraffic, gymnax",
          "a gymnax submodule first": "import jaxtraffic; import gymnax.sub; import gymnax",
          "after a find_spec probe": "import importlib.util, jaxtraffic; importlib.util.find_spec('gymnax'); "
                                     "import gymnax"}


def _python(code: str, *path: Path) -> str:
    env = {**os.environ, "JAX_PLATFORMS": "cpu", "PYTHONPATH": os.pathsep.join(map(str, (*path, REPO)))}
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300, env=env, cwd=REPO)
    assert out.returncode == 0, out.stderr
    return out.stdout.strip()


@pytest.fixture
def fake_gymnax(tmp_path) -> Path:
    (tmp_path / "gymnax").mkdir()
    (tmp_path / "gymnax" / "__init__.py").write_text(FAKE_GYMNAX)
    (tmp_path / "gymnax" / "sub.py").write_text("X = 1\n")
    return tmp_path


@pytest.mark.parametrize("order", ORDERS)
def test_gymnax_make_finds_the_id_in_either_import_order(order, fake_gymnax):
    code = (f"{ORDERS[order]}; import sys; factory, kw = gymnax.make('jaxtraffic/Gain-v0'); "
            "print(gymnax.registered_envs, factory.__name__, "
            "[type(f).__name__ for f in sys.meta_path].count('_GymnaxHook'))")
    # registered once, by jaxtraffic's factory, and the one-shot hook gone from sys.meta_path
    assert _python(code, fake_gymnax) == "['jaxtraffic/Gain-v0'] _make_gymnax_env 0"


def test_import_jaxtraffic_alone_imports_no_gymnax_and_leaves_one_hook(fake_gymnax):
    code = ("import sys, jaxtraffic; from jaxtraffic._registration import register_gymnax; register_gymnax(); "
            "print('gymnax' in sys.modules, [type(f).__name__ for f in sys.meta_path].count('_GymnaxHook'))")
    assert _python(code, fake_gymnax) == "False 1"  # (register_gymnax again: still one hook)


def test_no_hook_without_gymnax_installed(tmp_path):
    code = ("import importlib.util, sys, jaxtraffic; "
            "print(importlib.util.find_spec('gymnax') is None, "
            "[type(f).__name__ for f in sys.meta_path].count('_GymnaxHook'))")
    found = _python(code, tmp_path)
    assert found in ("True 0", "False 1")  # no gymnax: no hook; gymnax installed: a hook until it is imported


@pytest.mark.skipif(not available("gymnax"), reason="the [gymnax] extra is not installed")
@pytest.mark.parametrize("order", ["import gymnax, jaxtraffic", "import jaxtraffic, gymnax"])
def test_real_gymnax_makes_the_env_in_either_import_order(order):
    made = _python(f"{order}; env, p = gymnax.make('jaxtraffic/Gain-v0', n_points=21); "
                   "print(type(env).__name__, int(p.horizon))")
    assert made == "GainGymnaxEnv 1000"  # the default 100 s horizon, dt 0.1 s


# ----------------------------------------------------------------------------- the committed notebook
NOTEBOOK = REPO / "examples" / "quickstart.ipynb"


def _outputs() -> list[list[dict]]:
    import json

    nb = json.loads(NOTEBOOK.read_text())
    return [c["outputs"] for c in nb["cells"] if c["cell_type"] == "code"]


def test_the_committed_notebook_shows_its_outputs_small_and_plain():
    outputs = _outputs()
    assert all(outputs[1:]), "a code cell without output: execute the notebook before committing it"
    assert not [o for o in outputs[0] if o["output_type"] == "execute_result"]  # no stray value (the device count)
    texts = ["".join(o.get("text", "")) + str(o.get("data", {}).get("text/plain", "")) for c in outputs for o in c]
    assert not any("np.float" in t or "Traceback" in t for t in texts)
    batch = "".join(texts)
    assert "plant delay D = 4 s: final density L2" in batch and "veh/km" in batch
    images = [o["data"]["image/png"] for c in outputs for o in c if "image/png" in o.get("data", {})]
    assert 2 <= len(images) <= 3 and sum(map(len, images)) < 400_000  # (base64 characters)
    assert NOTEBOOK.stat().st_size < 500_000


def test_the_gymnasium_cell_says_when_gym_is_missing(monkeypatch, capsys):
    """Without gymnasium the cell prints how to install it (and shows nothing else)."""
    import builtins
    import json

    nb = json.loads(NOTEBOOK.read_text())
    cell = next("".join(c["source"]) for c in nb["cells"] if c["cell_type"] == "code"
                and "gymnasium.make" in "".join(c["source"]))
    real_import = builtins.__import__

    def no_gym(name, *args, **kwargs):
        if name.startswith("gymnasium"):
            raise ImportError("no gymnasium")
        return real_import(name, *args, **kwargs)

    monkeypatch.setattr(builtins, "__import__", no_gym)
    namespace: dict = {"N_POINTS": 41}
    exec(compile(cell, "quickstart.ipynb gymnasium cell", "exec"), namespace)  # noqa: S102
    assert namespace["frame_fig"] is None
    assert 'Gymnasium is not installed' in capsys.readouterr().out and '[gym]' in cell


# ----------------------------------------------------------------------------- trackers and ETAs
def test_each_run_has_its_own_tensorboard_folder_and_a_resume_continues_it(tmp_path):
    from jaxtraffic.runs.tracking import RUN_MARK, board_dir

    logs, run = tmp_path / "tb", tmp_path / "runs" / "default"
    first = board_dir(logs, run, resume=False)
    assert first.parent == logs and first.name.startswith("default_") and first.is_dir()
    assert (first / RUN_MARK).read_text().strip() == str(run.resolve())
    again = board_dir(logs, run, resume=False)  # a new run in the same directory (--overwrite): a new folder
    assert again != first and again.name.startswith(first.name)
    other = board_dir(logs, tmp_path / "elsewhere" / "default", resume=False)  # the same name, another run
    assert board_dir(logs, run, resume=True) == again  # the newest folder of this run, not the other's
    assert board_dir(logs, tmp_path / "elsewhere" / "default", resume=True) == other
    assert board_dir(logs, tmp_path / "new", resume=True).name.startswith("new_")  # nothing to continue: new
    assert len(list(logs.iterdir())) == 4


def test_eta_text_is_the_remaining_work_at_the_rate():
    from jaxtraffic.runs.session import eta_text

    assert eta_text(600, 2.0) == "ETA 5m00s" and eta_text(-5, 2.0) == "ETA 0m00s"
    assert eta_text(600, float("nan")) == eta_text(600, 0.0) == "ETA ?"  # a first, compiling chunk


def test_the_gradient_trainer_and_the_evaluation_show_an_eta(tmp_path, capsys):
    from jaxtraffic import backstepping, lyapunov
    from jaxtraffic.paper.scenarios import EvalConfig, run_robustness
    from jaxtraffic.runs.config import TrainConfig
    from jaxtraffic.runs.gradient.trainer import train_gradient

    config = TrainConfig.make(run={"algo": "gradient", "out_dir": str(tmp_path / "g"), "eval_horizon_s": 2.0},
                              plant={"n_points": 21},
                              grad={"train_horizon_s": 2.0, "steps_per_chunk": 1, "grad_steps": 3,
                                    "train_delays": (4.0,)})
    train_gradient(config)
    lines = [x for x in capsys.readouterr().out.splitlines() if x.startswith("[update")]
    assert len(lines) == 3 and "| ETA ?" in lines[0]  # the first chunk compiles: no rate yet
    assert "| ETA 0m0" in lines[1]  # one chunk left, well under a minute
    assert "| ETA 0m00s" in lines[2]  # (then " | beats backstepping" when it does)
    said: list[str] = []
    eval_config = EvalConfig(n_points=21, horizon_s=1.0, robust_delays=(2.0, 4.0), robust_alphas=(0.15,),
                             robust_horizon_s=1.0)
    run_robustness({"lyapunov": lyapunov(1.0), "backstepping": backstepping(4.0, 1.0)}, eval_config, said.append)
    assert len(said) == 2 and all(" | ETA " in s for s in said) and said[-1].endswith("ETA 0m00s")


def test_train_py_takes_mlflow_and_an_older_config_json_without_it_still_loads(tmp_path):
    from jaxtraffic.cli.train import config_from_args
    from jaxtraffic.runs.config import TrainConfig, config_from_json, config_json

    cfg = config_from_args(["ppo", "--mlflow", str(tmp_path / "ml"), "--tensorboard", str(tmp_path / "tb")])
    assert cfg.run.mlflow == str(tmp_path / "ml") and cfg.run.tensorboard == str(tmp_path / "tb")
    saved = config_json(TrainConfig.make(run={"out_dir": str(tmp_path / "r")}))
    del saved["config"]["run"]["mlflow"]  # a run of the same config version from before the flag
    assert config_from_json(saved).run.mlflow is None
    del saved["config"]["run"]["tensorboard"]  # any missing field: at its default
    assert config_from_json(saved).run.tensorboard is None


@pytest.mark.skipif(not (available("tensorboardX") and available("mlflow")), reason="needs [tb] and [mlflow]")
def test_a_run_logs_to_its_own_tensorboard_folder_with_its_config_and_to_mlflow(tmp_path):
    from mlflow import MlflowClient
    from test_loop import Counting

    from jaxtraffic.runs.config import TrainConfig, config_json
    from jaxtraffic.runs.loop import prepare, run_training

    def run(resume: bool) -> None:
        config = TrainConfig.make(run={"out_dir": str(tmp_path / "run"), "quiet": True, "resume": resume,
                                       "tensorboard": str(tmp_path / "tb"), "mlflow": str(tmp_path / "ml")})
        config, run_dir, saved = prepare(config)
        run_training(config, run_dir, saved, lambda: Counting(total=3 if not resume else 5, checkpoint_every=1),
                     lambda: config_json(config))

    run(resume=False)
    folders = list((tmp_path / "tb").iterdir())
    assert len(folders) == 1 and folders[0].name.startswith("run_")  # the run's own folder
    events = b"".join(p.read_bytes() for p in folders[0].glob("events.out.tfevents.*"))
    assert b"train/value" in events and b"config" in events and b"[run]" in events  # the scalars and config.toml
    run(resume=True)
    assert list((tmp_path / "tb").iterdir()) == folders  # a resume continues the run's folder
    client = MlflowClient(f"sqlite:///{(tmp_path / 'ml' / 'mlflow.db').absolute()}")
    runs = client.search_runs([client.get_experiment_by_name("jaxtraffic").experiment_id])
    assert len(runs) == 2 and {r.info.status for r in runs} == {"FINISHED"}
    first = min(runs, key=lambda r: r.info.start_time)
    assert first.info.run_name.startswith("run_") and first.data.params["run.tensorboard"] == str(tmp_path / "tb")
    assert [m.value for m in client.get_metric_history(first.info.run_id, "value")] == [1.0, 2.0, 3.0]

"""examples/quickstart.ipynb runs top to bottom (its code cells, in order, in one namespace, on a tiny grid),
its figures are figures, and a Jupyter kernel shows them: executed as Jupyter and nbconvert do (nbclient,
ipykernel: ``pip install -e ".[notebook]"``), the notebook's outputs hold PNG images, not ``<Figure ...>`` text."""

from __future__ import annotations

import json
from pathlib import Path

from extras import available, need

REPO = Path(__file__).resolve().parents[1]
NOTEBOOK = REPO / "examples" / "quickstart.ipynb"


def _code_cells() -> list[str]:
    nb = json.loads(NOTEBOOK.read_text())
    return ["".join(c["source"]) for c in nb["cells"] if c["cell_type"] == "code"]


def test_quickstart_notebook_runs(monkeypatch):
    from matplotlib.figure import Figure

    monkeypatch.setenv("JAXTRAFFIC_NOTEBOOK_SMALL", "1")
    cells = _code_cells()
    assert len(cells) >= 6 and cells[0].startswith("%matplotlib inline")  # the kernel displays figures inline
    namespace: dict = {"__name__": "__notebook__"}
    for i, source in enumerate(cells):  # IPython's line magics (%...) need a kernel: the test below runs them
        source = "\n".join(line for line in source.splitlines() if not line.startswith("%"))
        exec(compile(source, f"quickstart.ipynb cell {i}", "exec"), namespace)  # noqa: S102
    assert isinstance(namespace["fig"], Figure) and len(namespace["fig"].axes) == 2  # reward and L2 panels
    heat, runs = namespace["heat"], namespace["runs"]  # the space-time density maps, one per controller
    images = [ax.images[0].get_array() for ax in heat.axes if ax.images]
    n_t = len(runs["open loop"].trajectory.t)
    assert len(images) == 3 and all(im.shape == (41, n_t) for im in images)  # (position, time)
    frame_fig = namespace["frame_fig"]  # the rendered episode, when gymnasium is installed
    assert (frame_fig is None) != available("gymnasium")
    if frame_fig is not None:
        assert frame_fig.axes[0].images and frame_fig.axes[0].images[0].get_array().shape == (200, 400, 3)
    assert float(runs["backstepping"].metrics["final_rho_L2"]) < float(runs["open loop"].metrics["final_rho_L2"])


def test_quickstart_notebook_shows_its_figures_in_a_kernel(monkeypatch):
    """What ``jupyter nbconvert --execute`` (and Jupyter itself) gets: every figure cell's output is an image."""
    nbclient, nbformat = need("nbclient"), need("nbformat")
    need("ipykernel")
    monkeypatch.setenv("JAXTRAFFIC_NOTEBOOK_SMALL", "1")  # (the kernel inherits the environment)
    nb = nbformat.read(NOTEBOOK, as_version=4)
    nbclient.NotebookClient(nb, timeout=300, kernel_name="python3",
                            resources={"metadata": {"path": str(REPO)}}).execute()
    code = [c for c in nb.cells if c.cell_type == "code"]
    shown = [c for c in code if c.source.rstrip().splitlines()[-1] in ("fig", "heat", "frame_fig")]
    assert len(shown) == 3
    for cell in shown:
        kinds = [set(out.get("data", {})) for out in cell.outputs if out.output_type == "execute_result"]
        last = cell.source.rstrip().splitlines()[-1]
        if last == "frame_fig" and not available("gymnasium"):
            assert not kinds  # None: nothing to show, and a line that says why
            said = "".join(out.get("text", "") for out in cell.outputs if out.output_type == "stream")
            assert "Gymnasium is not installed" in said and "[gym]" in said, cell.outputs
            continue
        assert kinds and "image/png" in kinds[0], (last, cell.outputs)
    errors = [out for c in code for out in c.outputs if out.output_type == "error"]
    assert not errors

"""examples/quickstart.ipynb runs top to bottom (its code cells, in order, in one namespace, on a tiny grid),
and its figures are figures: what a user who opens it in Jupyter gets, without Jupyter."""

from __future__ import annotations

import json
from pathlib import Path

from extras import available

REPO = Path(__file__).resolve().parents[1]


def test_quickstart_notebook_runs(monkeypatch):
    from matplotlib.figure import Figure

    monkeypatch.setenv("JAXTRAFFIC_NOTEBOOK_SMALL", "1")
    nb = json.loads((REPO / "examples" / "quickstart.ipynb").read_text())
    cells = ["".join(c["source"]) for c in nb["cells"] if c["cell_type"] == "code"]
    assert len(cells) >= 5
    namespace: dict = {"__name__": "__notebook__"}
    for i, source in enumerate(cells):
        exec(compile(source, f"quickstart.ipynb cell {i}", "exec"), namespace)  # noqa: S102
    assert isinstance(namespace["fig"], Figure) and len(namespace["fig"].axes) == 2  # reward and L2 panels
    frame_fig = namespace["frame_fig"]  # the rendered episode, when gymnasium is installed
    assert (frame_fig is None) != available("gymnasium")
    if frame_fig is not None:
        assert frame_fig.axes[0].images and frame_fig.axes[0].images[0].get_array().shape == (200, 400, 3)
    runs = namespace["runs"]
    assert float(runs["backstepping"].metrics["final_rho_L2"]) < float(runs["open loop"].metrics["final_rho_L2"])

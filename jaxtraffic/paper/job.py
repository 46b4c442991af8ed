"""The main job's evaluation: every experiment on each plant, the comparison of the plants, the certificates of
the learned laws, and the first plant's REPORT.md written once, whole (``evaluate_plants``).

The first plant's outputs go to ``out_dir``, each other plant's to ``out_dir/NAME``. Each other plant's REPORT.md
is its own evaluation; the first plant's adds the plants' comparison (``paper.plants``) and the stability
certificates of the learned laws (``paper.certificate``), so no layer appends to a report another wrote.
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path
from typing import Any

import jax

from jaxtraffic.control.base import Controller
from jaxtraffic.io.files import atomic_write_text
from jaxtraffic.paper.certificate import certificate_section
from jaxtraffic.paper.driver import evaluate_plant
from jaxtraffic.paper.fair import FairStage
from jaxtraffic.paper.plants import compare_plants
from jaxtraffic.paper.scenarios import EvalConfig
from jaxtraffic.platform import distributed


def evaluate_plants(controllers: dict[str, Controller], configs: dict[str, EvalConfig], out_dir: str | Path,
                    meta: dict[str, Any], oracles: dict[str, dict | None] | None = None,
                    log: Callable[[str], None] = print, fair_stage: FairStage | None = None,
                    **options: Any) -> dict[str, dict[str, Any]]:
    """``evaluate_plant`` on each plant of ``configs`` (in order; the first is the main one), then the held-out
    comparison (``fair_stage``, on each plant's nominal; outputs in ``out_dir/fair/PLANT.*``), then every report
    written once; returns plant -> metrics. ``options``: ``evaluate_plant``'s keyword arguments
    (``learned_runs`` also feeds the certificate section, ``grids`` the comparison); ``oracles``: plant -> its
    map's oracle rows."""
    out_dir = Path(out_dir)
    first = next(iter(configs))
    results, reports = {}, {}
    for plant, eval_config in configs.items():
        out = out_dir if plant == first else out_dir / plant
        log(f"== {plant} plant: {eval_config.describe()} -> {out}")
        results[plant], reports[plant] = evaluate_plant(
            controllers, eval_config, out, {**meta, "plant": plant}, log=log,
            oracle=(oracles or {}).get(plant), **options)
        if plant != first and distributed.is_writer():
            atomic_write_text(out / "REPORT.md", reports[plant])
        jax.clear_caches()  # a plant's programs (hundreds) are not used again: their memory mappings released
    fair_text: list[str] = []
    for plant, eval_config in configs.items():
        n = fair_stage.scenarios(plant == first) if fair_stage is not None else 0
        if fair_stage is not None and n:
            fair_text += fair_stage.section(controllers, options.get("grids") or {}, plant, eval_config.nominal(),
                                            out_dir / "fair" if distributed.is_writer() else None, n, log) + [""]
            jax.clear_caches()
    if distributed.is_writer():
        report = reports[first]
        if len(results) > 1:
            _, plants_text = compare_plants(results, configs, out_dir, log=log)
            report = report.rstrip() + "\n\n" + plants_text
        section = certificate_section(options.get("learned_runs") or {}, out_dir, log=log)
        for part in (section, fair_text):
            if part:
                report = report.rstrip() + "\n\n" + "\n".join(part)
        atomic_write_text(out_dir / "REPORT.md", report)
    return results

"""A report that evaluate.py published (``cli.staging``), made for tests that need one in a folder."""

from __future__ import annotations

from pathlib import Path

from jaxtraffic.cli import staging


def previous_report(out: Path, files: dict[str, str] | None = None) -> Path:
    """Publish ``files`` (relative path -> text; default ``REPORT.md``: "earlier") into ``out`` through
    ``staging.Staging``, as an earlier evaluate.py would have; returns ``out``."""
    stage = staging.Staging(out)
    for rel, text in (files or {"REPORT.md": "earlier"}).items():
        (stage.work / rel).parent.mkdir(parents=True, exist_ok=True)
        (stage.work / rel).write_text(text)
    stage.publish()
    return out
